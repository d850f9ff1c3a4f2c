"""The rule that keeps an output from destroying an input (``dpc_jax._io``), the same for every command:
no output path may be, contain or lie inside an input or another output (by path, through links and
``..``, and by inode); a folder a command would replace must be one it made; an empty path is refused;
nothing is made beside a stream. Each command's refusal is one line, exit status 2, before any work.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from support import write_odometry

from dpc_jax._io import foreign_folder_problem, is_stdout, is_stream, overlap_problem
from dpc_jax.cli import main
from dpc_jax.data.poses_io import write_kitti_poses


def _one_error(err: str, needle: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in err, err
    return lines[0]


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def kitti(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 6-frame odometry root (sequence 00, poses/00.txt)."""
    root = tmp_path_factory.mktemp("rule") / "kitti"
    write_odometry(root, n=6)
    return root


# ----------------------------------------------------------------------------- the pure checks


def test_overlap_by_path(tmp_path: Path) -> None:
    gt = tmp_path / "gt.txt"
    gt.write_text("x")
    data = tmp_path / "data"
    data.mkdir()
    def problem(inputs: list, outputs: list) -> str:
        return str(overlap_problem(inputs, outputs))

    assert f"--json {gt}: is the input --gt {gt}" in problem([("--gt", gt)], [("--json", gt)])
    assert ": lies inside the input --root" in problem([("--root", data)], [("--out", data / "new" / "c")])
    assert ": contains the input --gt" in problem([("--gt", gt)], [("--export", tmp_path)])
    assert ": is the output --out" in problem([], [("--out", tmp_path / "x"), ("--report", tmp_path / "x")])
    outputs = [("--out", tmp_path / "out.txt"), ("--report", tmp_path / "report"), ("--csv", None)]
    assert overlap_problem([("--gt", gt), ("--root", data)], outputs) is None
    # A prefix of the name is not a parent folder.
    assert overlap_problem([("--root", data)], [("--out", tmp_path / "data2")]) is None


def test_overlap_through_links(tmp_path: Path) -> None:
    gt = tmp_path / "gt.txt"
    gt.write_text("x")
    (tmp_path / "soft.txt").symlink_to(gt)
    os.link(gt, tmp_path / "hard.txt")
    data = tmp_path / "data"
    data.mkdir()
    (tmp_path / "alias").symlink_to(data)
    for link in ("soft.txt", "hard.txt"):
        same = overlap_problem([("--gt", gt)], [("--out", tmp_path / link)])
        assert ": is the input --gt" in str(same), link
    inside = overlap_problem([("--root", data)], [("--out", tmp_path / "alias" / "x")])
    assert ": lies inside the input" in str(inside)
    contains = overlap_problem([("--root", tmp_path / "alias")], [("--out", tmp_path)])
    assert ": contains the input" in str(contains)


def test_overlap_through_dot_dot_and_relative_spellings(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "poses").mkdir()
    (tmp_path / "poses" / "gt.txt").write_text("x")
    monkeypatch.chdir(tmp_path)
    same = overlap_problem([("--gt", "poses/gt.txt")], [("--out", "./poses/../poses/gt.txt")])
    assert ": is the input" in str(same)
    assert ": lies inside the input" in str(overlap_problem([("--root", ".")], [("--out", "poses/new.txt")]))


def test_streams_replace_nothing_and_are_not_compared(tmp_path: Path) -> None:
    assert is_stream("/dev/null") and not is_stream(tmp_path / "new.txt")
    assert not is_stdout("/dev/null") and not is_stdout(tmp_path / "new.txt")
    assert overlap_problem([("--gt", "/dev/null")], [("--out", "/dev/null"), ("--csv", "/dev/null")]) is None


def test_foreign_folder(tmp_path: Path) -> None:
    label = "--out x"
    args = {"marker": "manifest.json", "made_by": "a cache"}
    assert foreign_folder_problem(tmp_path / "missing", label, **args) is None
    (tmp_path / "empty").mkdir()
    assert foreign_folder_problem(tmp_path / "empty", label, **args) is None
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "manifest.json").write_text("{}")
    assert foreign_folder_problem(tmp_path / "cache", label, **args) is None
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "important.txt").write_text("keep")
    problem = str(foreign_folder_problem(tmp_path / "mine", label, **args))
    assert problem.startswith("--out x: ") and "is not a cache (no manifest.json)" in problem
    (tmp_path / "file").write_text("x")
    assert "is not a folder" in str(foreign_folder_problem(tmp_path / "file", label, **args))


# ----------------------------------------------------------------------------- every command


@pytest.mark.parametrize("argv", [
    ["synth", "--out", ""],
    ["vo", "--kitti-odometry", "k", "--sequence", "00", "--out", ""],
    ["vo", "--kitti-odometry", "", "--sequence", "00", "--out", "t.txt"],
    ["prepare", "--kitti-odometry", "k", "--sequence", "00", "--prior", "p.txt", "--out", ""],
    ["prepare", "--kitti-odometry", "k", "--sequence", "00", "--prior", "", "--out", "c"],
    ["train", "--config", "c.py", "--workdir", ""],
    ["correct", "--checkpoint", "r", "--data", "c", "--out", "c.txt", "--report", ""],
    ["correct", "--checkpoint", "r", "--kitti-odometry", "k", "--sequence", "00", "--prior", "p",
     "--cache", "", "--out", "c.txt"],
    ["evaluate", "--gt", "g.txt", "--est", "e.txt", "--report", ""],
    ["evaluate", "--gt", "g.txt", "--est", "e.txt", "--json", ""],
    ["evaluate", "--gt", "g.txt", "--est", "e.txt", "--export", ""],
    ["demo", "--out", ""],
], ids=lambda argv: f"{argv[0]} {argv[argv.index('') - 1]}")
def test_empty_path_is_refused(argv: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                               capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    option = argv[argv.index("") - 1]
    assert f"argument {option}: expected a path, got an empty one" in err
    assert list(tmp_path.iterdir()) == []


def test_outputs_over_inputs_are_refused_before_any_work(
    kitti: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    gt, est = tmp_path / "gt.txt", tmp_path / "est.txt"
    poses = np.tile(np.eye(4), (6, 1, 1))
    poses[:, 0, 3] = np.arange(6.0)
    write_kitti_poses(gt, poses)
    write_kitti_poses(est, poses)
    export = tmp_path / "ex"
    export.mkdir()
    (export / "gt.kitti.txt").write_bytes(gt.read_bytes())
    run = tmp_path / "run" / "checkpoints"
    run.mkdir(parents=True)
    (run / "config.json").write_text("{}")
    cache = tmp_path / "cache" / "00"
    cache.mkdir(parents=True)
    (cache / "manifest.json").write_text("{}")
    (tmp_path / "link.txt").symlink_to(gt)
    correct = ["correct", "--checkpoint", tmp_path / "run", "--no-progress"]
    cases = {
        "--json {t}/gt.txt: is the input --gt {t}/gt.txt": [
            "evaluate", "--gt", gt, "--est", est, "--json", gt],
        "--json {t}/link.txt: is the input --gt {t}/gt.txt": [
            "evaluate", "--gt", gt, "--est", est, "--json", tmp_path / "link.txt"],
        "--export {t}/ex: contains the input --gt {t}/ex/gt.kitti.txt": [
            "evaluate", "--gt", export / "gt.kitti.txt", "--est", est, "--export", export],
        "--report {t}/X: is the output --json {t}/X": [
            "evaluate", "--gt", gt, "--est", est, "--json", tmp_path / "X", "--report", tmp_path / "X"],
        "--out {k}/poses/00.txt: lies inside the input --kitti-odometry {k}": [
            "vo", "--kitti-odometry", kitti, "--sequence", "00", "--out", kitti / "poses" / "00.txt"],
        "--out {k}/sequences: lies inside the input --kitti-odometry {k}": [
            "prepare", "--kitti-odometry", kitti, "--sequence", "00", "--prior", gt,
            "--out", kitti / "sequences"],
        "--out {t}: contains the input --prior {t}/gt.txt": [
            "prepare", "--kitti-odometry", kitti, "--sequence", "00", "--prior", gt, "--out", tmp_path],
        "--out {t}/gt.txt: is the input --prior {t}/gt.txt": [
            *correct, "--data", cache, "--prior", gt, "--out", gt, "--force"],
        "--report {t}/X: is the output --out {t}/X": [
            *correct, "--data", cache, "--out", tmp_path / "X", "--report", tmp_path / "X"],
        "--cache {k}/sequences: lies inside the input --kitti-odometry {k}": [
            *correct, "--kitti-odometry", kitti, "--sequence", "00", "--prior", gt,
            "--cache", kitti / "sequences", "--out", tmp_path / "c.txt"],
        "--adapt: the adapted network goes beside --out": [*correct, "--data", cache, "--out", "/dev/null",
                                                           "--adapt", "5"],
    }
    before = {root: _snapshot(root) for root in (kitti, tmp_path)}
    for needle, argv in cases.items():
        assert main([str(a) for a in argv]) == 2, needle
        _one_error(capsys.readouterr().err, needle.format(t=tmp_path, k=kitti))
    assert {root: _snapshot(root) for root in (kitti, tmp_path)} == before


def test_folders_a_command_did_not_make_are_refused(
    kitti: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    prior = tmp_path / "prior.txt"
    prior.write_bytes((kitti / "poses" / "00.txt").read_bytes())
    mine = tmp_path / "mine"
    for folder in ("00", "sequences/00", "data/sequences/test", "c.adapted"):
        (mine / folder).mkdir(parents=True)
        (mine / folder / "important.txt").write_text("keep")
    config = tmp_path / "c.py"
    config.write_text("CONFIG = {}\n")
    cases = {
        "--out {m}: {m}/00 holds files but is not a cache of `dpc-jax prepare` (no manifest.json)": [
            "prepare", "--kitti-odometry", kitti, "--sequence", "00", "--prior", prior, "--out", mine],
        "--cache {m}: {m}/00 holds files but is not a cache of `dpc-jax prepare`": [
            "correct", "--checkpoint", tmp_path / "run", "--kitti-odometry", kitti, "--sequence", "00",
            "--prior", prior, "--cache", mine, "--out", tmp_path / "c.txt"],
        "--out {m}: {m}/sequences/00 holds files but is not a sequence `dpc-jax synth` rendered": [
            "synth", "--out", mine, "--sequences", "1", "--frames", "10", "--overwrite"],
        "--workdir {m}: {m} holds files but is not a training run (no checkpoints/config.json)": [
            "train", "--config", config, "--workdir", mine],
        "--out {m}: {m}/data/sequences/test holds files but is not a sequence": ["demo", "--out", mine],
        "--adapt (beside --out {m}/c.txt): {m}/c.adapted holds files but is not an adapted network": [
            "correct", "--checkpoint", tmp_path / "run", "--kitti-odometry", kitti, "--sequence", "00",
            "--prior", prior, "--out", mine / "c.txt", "--adapt", "5"],
    }
    before = _snapshot(tmp_path)
    for needle, argv in cases.items():
        assert main([str(a) for a in argv]) == 2, needle
        _one_error(capsys.readouterr().err, needle.format(m=mine))
    assert _snapshot(tmp_path) == before


def test_the_rule_is_checked_before_jax_is_imported(kitti: Path, tmp_path: Path) -> None:
    """Refusals that open the sequence (for the name of the folder it would replace) or load a
    config still come before JAX: checked in a fresh interpreter, as conftest has imported JAX here."""
    prior = kitti / "poses" / "00.txt"
    mine = tmp_path / "mine"
    for folder in ("00", "run"):
        (mine / folder).mkdir(parents=True)
        (mine / folder / "important.txt").write_text("keep")
    commands = [
        ["prepare", "--kitti-odometry", kitti, "--sequence", "00", "--prior", prior, "--out", mine],
        ["correct", "--checkpoint", tmp_path / "run", "--kitti-odometry", kitti, "--sequence", "00",
         "--prior", prior, "--cache", mine, "--out", tmp_path / "c.txt"],
        ["evaluate", "--gt", prior, "--est", prior, "--json", prior],
        ["demo", "--out", mine],
    ]
    script = ("import sys; from dpc_jax.cli import main\n"
              f"statuses = [main(argv) for argv in {[[str(a) for a in argv] for argv in commands]!r}]\n"
              "print(statuses, 'jax' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.stdout.strip() == "[2, 2, 2, 2] False", done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 4 and all(" holds files but is not " in line or ": is the input " in line
                                   for line in lines), done.stderr


def test_nothing_is_made_beside_a_stream(kitti: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """``vo --out /dev/stdout`` makes no ``/dev/stdout.csv`` and prints only the trajectory there;
    ``evaluate --json /dev/stdout`` prints only the JSON."""
    made = [Path("/dev/stdout.csv"), Path("/dev/stdout.json")]
    capfd.readouterr()
    try:
        assert main(["vo", "--kitti-odometry", str(kitti), "--sequence", "00", "--out", "/dev/stdout",
                     "--no-progress"]) == 0
        assert not any(path.exists() for path in made)
    finally:
        for path in made:
            if path.is_file():
                path.unlink()
    rows = [line.split() for line in capfd.readouterr().out.splitlines()]
    assert len(rows) == 6 and all(len(row) == 12 for row in rows)
    gt = kitti / "poses" / "00.txt"
    assert main(["evaluate", "--gt", str(gt), "--est", str(gt), "--json", "/dev/stdout"]) == 0
    assert "m_ate" in json.dumps(json.loads(capfd.readouterr().out))


def test_a_run_resumed_from_its_own_config_is_not_an_overlap(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`train --config RUN/checkpoints/config.json --workdir RUN --resume` reads the config the run
    wrote and does not rewrite it; without --resume the same config inside the workdir is refused."""
    from dpc_jax import config as config_lib
    from dpc_jax.training.train_config import TrainConfig

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    own = run / "checkpoints" / "config.json"
    config = TrainConfig(cache_root=str(tmp_path / "no_cache"), validation_sequences=("01",))
    config_lib.save_json(own, config)
    before = own.read_bytes()
    assert main(["train", "--config", str(own), "--workdir", str(run), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "no_cache" in err and "inside" not in err and "contains" not in err, err
    assert main(["train", "--config", str(own), "--workdir", str(run)]) == 2
    assert "--workdir" in capsys.readouterr().err
    assert own.read_bytes() == before


def test_files_a_command_did_not_write_are_never_replaced(
    kitti: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``evaluate --report/--export`` and ``correct --report`` into a folder holding a user's file of a name
    they write are refused before any work; into a folder of other files they write theirs beside them and
    record them (``.dpc-jax-files``), so that a rerun replaces its own files and nothing else."""
    from dpc_jax._io import OWN_FILES, foreign_files_problem, record_own_files
    from dpc_jax.report.evaluation_report import REPORT_FILES

    gt = kitti / "poses" / "00.txt"
    est = tmp_path / "est.txt"
    est.write_bytes(gt.read_bytes())
    folders = {"u10": "report.md", "u11": "metrics.json", "u12": "est.kitti.txt", "shared": "notes.txt"}
    for name, file in folders.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / file).write_text("the user's")
    evaluate = ["evaluate", "--gt", gt, "--est", est]
    u10, u11, u12, shared = (tmp_path / name for name in folders)
    not_ours = "exists and was not written by dpc-jax"
    cases = {
        f"--report {u10}: {u10 / 'report.md'} {not_ours}": [*evaluate, "--report", u10],
        f"--export {u12}: {u12 / 'est.kitti.txt'} {not_ours}": [*evaluate, "--export", u12],
        f"--report {u11}: {u11 / 'metrics.json'} {not_ours}": [
            "correct", "--checkpoint", tmp_path / "run", "--kitti-odometry", kitti, "--sequence", "00",
            "--prior", gt, "--out", tmp_path / "c.txt", "--report", u11],
    }
    before = _snapshot(tmp_path)
    for needle, argv in cases.items():
        assert main([str(a) for a in argv]) == 2, needle
        _one_error(capsys.readouterr().err, needle)
    assert _snapshot(tmp_path) == before
    assert foreign_files_problem(tmp_path / "missing", REPORT_FILES, "--report x") is None
    for _ in range(2):  # the second round replaces the files the first recorded as its own
        assert main([str(a) for a in [*evaluate, "--report", shared]]) == 0
        capsys.readouterr()
    assert sorted(p.name for p in shared.iterdir()) == sorted({*REPORT_FILES, "notes.txt", OWN_FILES})
    recorded = "".join(f"{name}\tevaluate --report\n" for name in sorted(REPORT_FILES))
    assert (shared / OWN_FILES).read_text() == recorded
    # One folder, one command's results: another command's (or option's) files are never mixed in.
    correct_report = tmp_path / "correct_report"
    correct_report.mkdir()
    for name in ("report.md", "metrics.json", "summary.json"):
        (correct_report / name).write_text("correct's")
    record_own_files(correct_report, correct_report, ["report.md", "metrics.json", "summary.json"],
                     writer="correct --report")
    before = _snapshot(tmp_path)
    for option, folder, other in (("--export", shared, "evaluate --report"),
                                  ("--report", correct_report, "correct --report")):
        assert main([str(a) for a in [*evaluate, option, folder]]) == 2
        _one_error(capsys.readouterr().err, f"{option} {folder}: {folder} holds the results of `dpc-jax "
                   f"{other}`")
    assert _snapshot(tmp_path) == before
    assert (shared / "notes.txt").read_text() == "the user's"


def test_files_named_after_an_output_are_replaced_only_where_a_command_recorded_them(tmp_path: Path) -> None:
    """``beside_problem``/``record_beside``: a file the user did not name (``OUT.csv``) that exists is
    refused until a command recorded it as its own, in place or staged with an output set (where the record
    lands with the files, all or nothing: nothing without a commit)."""
    from dpc_jax._io import OWN_FILES, OutputSet, atomic_write, beside_problem, record_beside

    csv, summary = tmp_path / "o" / "a.csv", tmp_path / "o" / "a.json"
    csv.parent.mkdir()
    csv.write_text("the user's")
    assert beside_problem([("--out a.txt (its CSV)", csv), ("--out a.txt (its .json summary)", None)]) == (
        f"--out a.txt (its CSV): {csv} exists and was not written by dpc-jax (it is not listed in "
        f"{csv.parent / OWN_FILES}), and this command would replace it; move it away or give the output "
        "another name")
    csv.unlink()
    with OutputSet() as outputs:  # not committed: neither the file nor the record is made
        atomic_write(outputs.file(summary), "{}")
        record_beside([summary], outputs)
    assert sorted(p.name for p in csv.parent.iterdir()) == []
    with OutputSet() as outputs:
        atomic_write(outputs.file(summary), "{}")
        record_beside([summary], outputs)
        outputs.commit()
    record_beside([csv])
    csv.write_text("a run's")
    assert beside_problem([("x", csv), ("y", summary)]) is None
    assert (csv.parent / OWN_FILES).read_text() == "a.csv\na.json\n"
