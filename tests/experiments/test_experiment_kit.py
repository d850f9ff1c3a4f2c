"""The experiment scripts' kit (``dpc_jax.experiments``): resumable records and measured stages with their
stamp, the measurement of a process, the synthetic world and planted priors, the scripts' plumbing, the
demo's config at a seed and shared inputs, and a protocol run reused when finished."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dpc_jax.experiments import script
from dpc_jax.experiments.records import Records
from dpc_jax.pipelines.protocol import WORKDIR_MARKER, claim_workdir

ROOT = Path(__file__).resolve().parents[2]


def test_a_record_is_reused_only_with_its_key_and_keeps_its_own_stamp(tmp_path: Path) -> None:
    records = Records(tmp_path / "cells", {"machine": "m", "commit": "c"})
    assert records.read("a") is None and records.done("a", {"n": 1}) is None
    stored = records.write("a", {"key": {"n": (1, 2)}, "value": 3})
    assert stored == {"key": {"n": (1, 2)}, "value": 3, "machine": "m", "commit": "c"}
    assert records.done("a", {"n": (1, 2)})["value"] == 3  # a tuple key matches its JSON list
    assert records.done("a", {"n": (1, 3)}) is None
    # A record measured again keeps the stamp of its training.
    records.write("b", {"value": 4, "machine": "trained elsewhere"})
    assert [r["machine"] for r in records.all()] == ["m", "trained elsewhere"]


def test_a_stage_runs_once_while_its_settings_hold(tmp_path: Path) -> None:
    from dpc_jax.experiments.process import Stages

    marks = tmp_path / "ran.txt"
    command = [sys.executable, "-c", f"open({str(marks)!r}, 'a').write('x')"]
    stages = Stages(tmp_path, {"commit": "c"})
    first = stages.run("s", {"n": 1}, [command, command], count=2, unit="frames", bytes=lambda: 7)
    assert marks.read_text() == "xx" and first["bytes"] == 7 and first["commit"] == "c"
    assert first["wall_s"] > 0 and (tmp_path / "logs" / "s_1.log").is_file()
    assert stages.run("s", {"n": 1}, [command], count=1) == first and marks.read_text() == "xx"
    stages.run("s", {"n": 2}, [command], count=1)
    assert marks.read_text() == "xxx"


def test_a_process_is_measured_from_outside(tmp_path: Path) -> None:
    """60 MB the process allocates count as anonymous memory; 60 MB of a file it maps and reads count in
    the kernel's peak RSS only (page cache); its CPU time is its own."""
    from dpc_jax.experiments.process import measure

    data = tmp_path / "data.bin"
    data.write_bytes(b"\1" * 60_000_000)
    code = ("import numpy as np, time; a = np.ones(60_000_000 // 8); "
            f"m = np.memmap({str(data)!r}, mode='r'); s = int(m[::4096].sum()); "
            "t = time.process_time(); x = 0\nwhile time.process_time() - t < 0.3: x += 1\n"
            "time.sleep(0.3); print(s, a.sum())")
    measured = measure([sys.executable, "-c", code], tmp_path / "log.txt")
    assert 60 <= measured.peak_anon_mb < 150
    assert measured.peak_rss_mb >= measured.peak_anon_mb + 45
    assert 0.3 <= measured.cpu_s < measured.wall_s
    with pytest.raises(RuntimeError, match=r"exit 3; .*log2\.txt\): boom"):
        measure([sys.executable, "-c", "import sys; print('boom'); sys.exit(3)"], tmp_path / "log2.txt")


@pytest.mark.slow
def test_a_world_renders_its_sequences_once_from_its_seed(tmp_path: Path) -> None:
    from dpc_jax.experiments.world import World

    world = World((16, 24), 5, {"moving_objects": 1})
    command = world.command(tmp_path, {"a": (3, 0), "b": (4, 7)})
    subprocess.run(command, check=True, capture_output=True)  # a process of its own, as a stage measures it
    recorded = json.loads((tmp_path / "sequences" / "b" / "synth.json").read_text())["config"]
    assert (recorded["seed"], recorded["frames"], recorded["height"]) == (12, 4, 16)
    assert recorded["moving_objects"] == 1
    assert world.render(tmp_path, {"a": (3, 0), "b": (4, 7)}, say=print) == []  # finished: kept


def test_a_planted_prior_is_the_ground_truth_of_its_sequence_with_the_error(tmp_path: Path) -> None:
    from dpc_jax.data.poses_io import write_kitti_poses
    from dpc_jax.experiments.world import planted
    from dpc_jax.synth.planted_prior import planted_prior

    gt = np.tile(np.eye(4), (5, 1, 1))
    gt[:, 2, 3] = np.arange(5.0)
    (tmp_path / "poses").mkdir()
    write_kitti_poses(tmp_path / "poses" / "s.txt", gt)
    bias, spread = np.array([1e-3, 0.0, 0.0]), np.array([0.0, 2e-4, 0.0])
    np.testing.assert_array_equal(planted(tmp_path, "s", bias, spread, 3),
                                  planted_prior(gt, bias, spread, seed=3))


def test_a_script_claims_its_outputs_says_one_line_and_publishes(tmp_path: Path, capsys) -> None:
    page = tmp_path / "page.md"
    page.write_text("# p\n<!-- results:begin -->\n<!-- results:end -->\n")
    blank = tmp_path / "blank.md"
    blank.write_text("no block\n")
    with pytest.raises(ValueError, match="no <!-- results:begin -->"):  # checked before the folder is made
        script.claim(tmp_path / "w", script="ablation.py", page=blank)
    assert not (tmp_path / "w").exists()
    assert script.claim(tmp_path / "w", script="ablation.py", page=page) == tmp_path / "w"
    assert (tmp_path / "w" / WORKDIR_MARKER).read_text().splitlines()[1:] == ["ablation"]
    # One script's work folder is another's only where the two are documented to share one.
    excerpt = tmp_path / "excerpt"
    for name in ("experiments/protocols/kitti_raw_excerpt.py", "excerpt_ground_truth", "kitti_raw_excerpt"):
        assert script.claim(excerpt, script=name) == excerpt
    with pytest.raises(ValueError, match=f"--workdir {excerpt}: {excerpt} is the work folder of "
                       "kitti_raw_excerpt, excerpt_ground_truth, and kitti_raw_drives would write"):
        script.claim(excerpt, script="kitti_raw_drives.py")
    assert script.refuse("study", ValueError("bad"), 1) == 1
    script.publish("# Title\n\nthe table", page, ROOT / "experiments" / "studies" / "ablation.py")
    out, err = capsys.readouterr()
    assert err == "study: error: bad\n" and out.startswith("# Title\n\nthe table\nresults page: ")
    assert "the table" in page.read_text() and "Written by `ablation.py`" in page.read_text()


def test_the_real_data_comes_from_the_variable_else_from_beside_a_checkout(tmp_path: Path,
                                                                            monkeypatch) -> None:
    """A data option's default: ``$DPC_JAX_DATA``'s folder when the variable is set, else ``../shared/data``
    beside the checkout the package runs from, and only from a checkout (a ``pyproject.toml`` two levels
    above the kit), never beside an installed package; without one, the script names the option."""
    import argparse
    import importlib.util

    (tmp_path / "data" / "kitti-raw").mkdir(parents=True)
    monkeypatch.setenv(script.DATA_VARIABLE, str(tmp_path / "data"))
    assert script.data_default("kitti-raw") == tmp_path / "data" / "kitti-raw"
    assert script.data_default("kitti-libviso2") is None
    parser = argparse.ArgumentParser()
    script.add_data_option(parser, "--libviso2", "kitti-libviso2", metavar="DIR", help="the .mat files")
    refusal = ("--libviso2: not given, and no default found (in $DPC_JAX_DATA when it is set, else in "
               "../shared/data beside the checkout); pass --libviso2 DIR or set DPC_JAX_DATA=DIR")
    with pytest.raises(ValueError, match=f"^{re.escape(refusal)}$"):
        script.data_given(parser.parse_args([]).libviso2, "--libviso2")
    assert script.data_given(parser.parse_args(["--libviso2", "m"]).libviso2, "--libviso2") == Path("m")
    # The same kit in a folder laid out as an installed package beside a shared/data/kitti-raw: found only
    # once that folder is a checkout.
    monkeypatch.delenv(script.DATA_VARIABLE)
    copy = tmp_path / "site" / "lib" / "dpc_jax" / "experiments" / "script.py"
    copy.parent.mkdir(parents=True)
    copy.write_text(Path(script.__file__).read_text())
    (tmp_path / "site" / "shared" / "data" / "kitti-raw").mkdir(parents=True)
    spec = importlib.util.spec_from_file_location("installed_script", copy)
    assert spec is not None and spec.loader is not None
    installed = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(installed)
    assert installed.data_default("kitti-raw") is None
    (tmp_path / "site" / "lib" / "pyproject.toml").write_text("")
    assert installed.data_default("kitti-raw") == tmp_path / "site" / "shared" / "data" / "kitti-raw"


def test_every_script_ends_on_ctrl_c_in_one_line_with_130(capsys) -> None:
    """``interruptible``: a KeyboardInterrupt is one line and exit status 130 (as the commands), not a
    traceback; every script's ``__main__`` goes through it."""

    def stopped() -> int:
        raise KeyboardInterrupt

    assert script.interruptible(stopped, "/x/kitti_raw_excerpt.py") == 130
    assert capsys.readouterr().err == ("kitti_raw_excerpt.py: interrupted; what it finished is kept, and the "
                                       "same command resumes\n")
    assert script.interruptible(lambda: 3, "s.py") == 3
    scripts = sorted((ROOT / "experiments").glob("*/*.py"))
    mains = {path.name: path.read_text().split('if __name__ == "__main__":')[-1] for path in scripts}
    through = re.compile(r"sys\.exit\((kit\.)?interruptible\(main, __file__\)\)")
    assert len(mains) >= 15 and all(through.search(text) for text in mains.values()), mains


def test_every_scripts_help_keeps_its_line_continuations() -> None:
    """A script's docstring is its ``--help``, verbatim: a command continued with ``\\`` keeps the
    backslash and its line break (in a plain string literal they vanish, and the two lines run together)."""
    import ast

    for path in sorted((ROOT / "experiments").glob("**/*.py")):
        tree = ast.parse(path.read_text())
        if not (tree.body and isinstance(tree.body[0], ast.Expr)):
            continue
        source = ast.get_source_segment(path.read_text(), tree.body[0]) or ""
        continued = sum(line.endswith("\\") for line in source.splitlines())
        assert (ast.get_docstring(tree, clean=False) or "").count("\\\n") == continued, path


def test_a_demo_config_at_a_seed_merges_its_training(tmp_path: Path) -> None:
    from dpc_jax.experiments.demos import demo_config, share

    path = tmp_path / "demo.py"
    path.write_text("CONFIG = {'adapt_steps': 0, 'training': {'epochs': 3, 'batch_size': 4}}\n")
    config = demo_config(path, 7, {"test_frames": 20, "training": {"epochs": 1}})
    assert (config.seed, config.adapt_steps, config.test_frames) == (7, 0, 20)
    assert config.training == {"epochs": 1, "batch_size": 4}
    source, target = tmp_path / "a", tmp_path / "b"
    (source / "data").mkdir(parents=True)
    (source / "vo").mkdir()
    share(source, target, ("data", "vo", "cache"))
    assert (target / "data").is_symlink() and (target / "vo").is_symlink()
    assert not (target / "cache").exists()  # nothing to share
    assert claim_workdir(target) == target  # the script of the second run takes the folder
    (target / "vo").unlink()
    (target / "vo").mkdir()
    share(source, target, ("vo",))
    assert not (target / "vo").is_symlink()  # a folder of its own is kept


def test_a_finished_protocol_run_is_read_not_run_again(tmp_path: Path, capsys) -> None:
    from dpc_jax.experiments.folds import (
        Context,
        Plan,
        add_protocol_arguments,
        finished_protocol,
        run_protocol,
    )

    config = ROOT / "experiments" / "protocols" / "configs" / "kitti_stereo_dpc.py"
    planned: list[Context] = []

    def plan(context: Context) -> Plan:
        planned.append(context)
        context.claim([])
        return Plan([], "No folds", "Nothing ran.")

    parser = script.new_parser("a protocol")
    add_protocol_arguments(parser, config)
    said: list[str] = []
    for _ in range(2):
        results = finished_protocol("p.py", parser, plan, tmp_path / "w", ["--smoke"], {"v": 1}, said.append)
        assert results == []
    assert len(planned) == 1 and said == [f"{tmp_path / 'w'}: finished, reused"]
    assert planned[0].select == "gradient" and planned[0].overrides["epochs"] == 1  # the config's, --smoke
    assert "SMOKE RUN" in (tmp_path / "w" / "results.md").read_text()
    assert json.loads((tmp_path / "w" / "results.json").read_text()) == []
    missing = tmp_path / "none.py"
    argv = ["--workdir", str(tmp_path / "v"), "--config", str(missing)]
    assert run_protocol("p.py", parser, plan, argv) == 2
    assert capsys.readouterr().err == f"p: error: {missing}: config file not found\n"
    assert len(planned) == 1 and not (tmp_path / "v").exists()
