"""The experiment scripts (``experiments/protocols``, ``experiments/studies``) under the output rule of
the commands (``dpc_jax.pipelines.protocol.claim_workdir`` over ``dpc_jax._io``): a work folder that is
empty, an input or inside one, or a folder no script made is refused in one line with exit status 2
before any work, every input byte-identical; a folder a script made carries a marker, and a rerun (or
another script sharing it) is allowed. Every refusal here stops before JAX work; nothing trains.
"""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
from conftest import load_script
from support import CU, CV, FU, FV, fixture_poses, projection_row, write_odometry

from dpc_jax.data.poses_io import write_kitti_poses
from dpc_jax.pipelines.protocol import WORKDIR_MARKER, claim_workdir

ROOT = Path(__file__).resolve().parents[2]
PROTOCOLS, STUDIES = ROOT / "experiments" / "protocols", ROOT / "experiments" / "studies"
DATE = "2011_09_26"


def _snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every entry under ``folder``: a file's bytes, None for a folder (so a new empty folder shows)."""
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() else None
            for p in sorted(folder.rglob("*"))}


def _one_error(err: str, needle: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in err, err
    return lines[0]


def _write_raw(root: Path, n: int = 4) -> Path:
    """A tiny KITTI raw root: drives 0001 and 0005 of 2011_09_26 (colour pairs of n 20×32 frames) and
    their libviso2 ``.mat`` files, as the real-data scripts' configs name them."""
    rng = np.random.default_rng(0)
    day = root / DATE
    for drive in ("0001", "0005"):
        sync = day / f"{DATE}_drive_{drive}_sync"
        for camera in ("image_02", "image_03"):
            (sync / camera / "data").mkdir(parents=True)
            for k in range(n):
                image = rng.integers(0, 256, (20, 32, 3), dtype=np.uint8)
                assert cv2.imwrite(str(sync / camera / "data" / f"{k:010d}.png"), image)
            (sync / camera / "timestamps.txt").write_text(
                "".join(f"2011-09-26 13:02:{25 + k * 0.1:012.9f}\n" for k in range(n)))
        poses = np.moveaxis(fixture_poses(n), 0, -1)
        buffer = io.BytesIO()
        scipy.io.savemat(buffer, {"poses_gt": poses, "poses_est": poses, "convention": "Twv"})
        (root / "libviso2").mkdir(exist_ok=True)
        (root / "libviso2" / f"stereo_{DATE}_drive_{drive}.mat").write_bytes(buffer.getvalue())
    (day / "calib_cam_to_cam.txt").write_text(
        f"P_rect_02: {projection_row(FU, CU, FV, CV, FU * 0.06)}\n"
        f"P_rect_03: {projection_row(FU, CU, FV, CV, FU * (0.06 - 0.54))}\n")
    return root


@pytest.fixture(scope="module")
def raw(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_raw(tmp_path_factory.mktemp("experiment_outputs") / "RAW")


# ----------------------------------------------------------------------------- the shared function


def test_claim_workdir_marks_what_it_made_and_refuses_the_rest(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    (data / "x.txt").write_text("input")
    work = tmp_path / "work"
    assert claim_workdir(work, [("--data", data)]) == work
    assert (work / WORKDIR_MARKER).is_file()
    (work / "results.md").write_text("a result")
    # A rerun, or another script sharing the folder, is allowed; the marker is not rewritten.
    marker = (work / WORKDIR_MARKER).stat().st_mtime_ns
    assert claim_workdir(work, [("--data", data)]) == work
    assert (work / WORKDIR_MARKER).stat().st_mtime_ns == marker
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    refusals = [  # (work folder, inputs, file outputs, the message)
        ("", [], [], "--workdir: expected a path, got an empty one"),
        (data, [("--data", data)], [], f"--workdir {data}: is the input --data {data}"),
        (data / "sub" / ".." / "runs", [("--data", data)], [], "lies inside the input --data"),
        (user, [], [], f"--workdir {user}: {user} holds files but is not the work folder of an experiment"),
        (work, [], [("--json", "")], "--json: expected a path, got an empty one"),
        (None, [("--data", data)], [("--json", data / "f.json")], "--json {data}/f.json: lies inside"),
    ]
    for folder, inputs, files, needle in refusals:
        with pytest.raises(ValueError) as caught:
            claim_workdir(folder, inputs, files=files)
        message = str(caught.value)
        assert needle.format(data=data) in message and "\n" not in message, message
    assert sorted(p.name for p in user.iterdir()) == ["notes.txt"]
    assert sorted(p.name for p in data.iterdir()) == ["x.txt"]
    # A work folder of an earlier version is taken by creating the marker.
    (user / WORKDIR_MARKER).write_text("")
    assert claim_workdir(user) == user


# ----------------------------------------------------------------------------- the real-data scripts


SCRIPTS = {"kitti_raw_excerpt": (PROTOCOLS, ["--smoke"]), "kitti_raw_drives": (PROTOCOLS, ["--smoke"]),
           "excerpt_ground_truth": (STUDIES, [])}


@pytest.mark.parametrize("name", list(SCRIPTS))
def test_real_data_scripts_refuse_a_workdir_over_their_inputs(
    name: str, raw: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The issue's cases: ``""`` (the current folder), the input root, its libviso2/ folder,
    ``RAW/sub/../runs`` and a user's folder; exit 2, one line, nothing written anywhere."""
    folder, extra = SCRIPTS[name]
    script = load_script(folder / f"{name}.py")
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    other = tmp_path / "other"  # the work folder of a script none of them shares with
    claim_workdir(other, owner="ablation")
    (other / "results.md").write_text("ablation's")
    monkeypatch.chdir(tmp_path)
    before = {root: _snapshot(root) for root in (raw, tmp_path)}
    cases = {
        "": "argument --workdir: expected a path, got an empty one",
        str(raw): f"--workdir {raw}: is the input --kitti-raw {raw}",
        str(raw / "libviso2"): f"--workdir {raw / 'libviso2'}: lies inside the input --kitti-raw",
        f"{raw}/sub/../runs": "lies inside the input --kitti-raw",
        str(user): f"--workdir {user}: {user} holds files but is not the work folder of an experiment script",
        str(other): f"--workdir {other}: {other} is the work folder of ablation, and {name} would write",
    }
    for workdir, needle in cases.items():
        argv = ["--kitti-raw", str(raw), "--workdir", workdir, "--no-progress", *extra]
        if workdir:
            assert script.main(argv) == 2, workdir
        else:
            with pytest.raises(SystemExit) as exited:  # argparse's refusal of the option's value
                script.main(argv)
            assert exited.value.code == 2
        err = capsys.readouterr().err
        assert needle in err and "Traceback" not in err, (workdir, err)
        if workdir:
            _one_error(err, needle)
    assert {root: _snapshot(root) for root in (raw, tmp_path)} == before


# ----------------------------------------------------------------------------- every other script


def _odometry(root: Path) -> tuple[Path, Path]:
    """A 6-frame odometry root with sequences 00, 02, 05 and a folder of their priors (KITTI text)."""
    priors = root / "priors"
    priors.mkdir(parents=True)
    for name in ("00", "02", "05"):
        written = write_odometry(root / "kitti", name=name)
        write_kitti_poses(priors / f"{name}.txt", written["poses"])
    return root / "kitti", priors


def test_every_other_script_claims_its_outputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Each script's own inputs and outputs: an output over an input, or a folder no script made."""
    kitti, priors = _odometry(tmp_path / "in")
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    demo = tmp_path / "demo"
    demo.mkdir()
    (demo / "summary.json").write_text("{}")
    config = tmp_path / "bias.py"
    config.write_text(f"CONFIG = {{'cache_root': {str(user / 'cache')!r}, 'validation_sequences': ['01']}}\n")
    odometry = ["--kitti-odometry", str(kitti), "--priors", str(priors), "--sequences", "00", "02", "05"]
    cases = [
        (PROTOCOLS, "kitti_stereo_dpc", [*odometry, "--test", "00", "--workdir", str(priors)],
         f"--workdir {priors}: is the input --priors {priors}"),
        (PROTOCOLS, "kitti_ss_dpc", [*odometry, "--fold", "stereo_val00", "--workdir", str(kitti / "w")],
         f"--workdir {kitti / 'w'}: lies inside the input --kitti-odometry"),
        (STUDIES, "ablation", ["--workdir", str(user)], f"--workdir {user}: {user} holds files but is not"),
        (STUDIES, "demo_seeds", ["--workdir", str(user)], f"--workdir {user}: {user} holds files but is not"),
        (STUDIES, "acceptance_depth", [str(demo), "--out", str(demo / "out")],
         f"--out {demo / 'out'}: lies inside the input DEMO_OUT {demo}"),
        (STUDIES, "bias_recovery", ["--config", str(config), "--out", str(user)],
         f"--out {user}: {user} holds files but is not"),
        (STUDIES, "linear_baseline", ["--data", str(priors), "--json", str(priors / "figures.json")],
         f"--json {priors / 'figures.json'}: lies inside the input --data {priors}"),
        (STUDIES, "paper_scale", ["--workdir", str(user)],
         f"--workdir {user}: {user} holds files but is not"),
        (STUDIES, "supervised_comparison", ["--workdir", str(user), "--skip-drives"],
         f"--workdir {user}: {user} holds files but is not"),
        (STUDIES, "live_agreement",
         ["--demo", str(user), "--drives", str(user), "--workdir", str(tmp_path / "w")],
         f"--demo {user}: not a finished `dpc-jax demo --out` folder (no summary.json)"),
    ]
    before = _snapshot(tmp_path)
    for folder, name, argv, needle in cases:
        assert load_script(folder / f"{name}.py").main(argv) == 2, name
        _one_error(capsys.readouterr().err, needle)
    assert _snapshot(tmp_path) == before and not (tmp_path / "w").exists()


def test_priors_vo_beside_a_folder_vo_is_refused_as_ambiguous(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--priors vo`` (our VO) where a folder ``vo`` of priors exists (the README's chain makes one): one
    line saying how to name either, before any work; ``./vo`` is the folder."""
    from dpc_jax.pipelines.protocol import priors_argument

    (tmp_path / "vo").mkdir()
    monkeypatch.chdir(tmp_path)
    for name in ("kitti_stereo_dpc", "kitti_ss_dpc"):
        with pytest.raises(SystemExit) as exited:
            load_script(PROTOCOLS / f"{name}.py").main(["--kitti-odometry", "k", "--priors", "vo",
                                                        "--workdir", "w"])
        assert exited.value.code == 2
        assert "argument --priors: 'vo' means our stereo VO, and there is a folder ./vo here: give ./vo" in (
            capsys.readouterr().err)
    assert priors_argument("./vo") == "./vo" and sorted(p.name for p in tmp_path.iterdir()) == ["vo"]
    monkeypatch.chdir(tmp_path / "vo")
    assert priors_argument("vo") == "vo"


def test_bias_recovery_writes_where_out_says_with_the_config_as_shipped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--out DIR`` needs no edit of the config (its caches go to DIR/cache, which the script makes), and
    the default is ``runs/bias_recovery`` in the current folder, not in the checkout."""
    study = load_script(STUDIES / "bias_recovery.py")
    made: list[tuple[Path, str]] = []

    def make_data(out: Path, config: object, args: object) -> None:
        made.append((out, config.cache_root))
        raise KeyboardInterrupt  # stop before the work: what it would write is known

    monkeypatch.setattr(study, "make_data", make_data)
    monkeypatch.chdir(tmp_path)
    for argv, out in (([], Path("runs/bias_recovery")), (["--out", str(tmp_path / "elsewhere")],
                                                          tmp_path / "elsewhere")):
        with pytest.raises(KeyboardInterrupt):
            study.main(argv)
        assert made[-1] == (out, str((out / "cache").resolve()))
    assert (tmp_path / "runs" / "bias_recovery").is_dir()


def test_the_results_table_says_when_the_test_was_off() -> None:
    """kitti_stereo_dpc.py's table said "trained (full)" under "what its acceptance test let through"
    when the protocol had the test off (acceptance False): what was forced now says so."""
    from dpc_jax.pipelines.protocol import applied_label
    from dpc_jax.results.acceptance import Acceptance

    assert applied_label("trained", Acceptance(0.01, component="full", forced=True)) == (
        "trained (full, test off: forced)")
    assert applied_label("adapted", Acceptance(0.01, component="rotation")) == "adapted (rotation)"
    assert applied_label("prior", Acceptance(0.01)) == "prior"
