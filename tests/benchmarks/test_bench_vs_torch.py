"""benchmarks/bench_vs_torch.py: its checks of the PyTorch side, its table, and one real run of
ours against a stand-in for PyTorch (no timing is asserted)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "bench_vs_torch.py"


def _module():
    spec = importlib.util.spec_from_file_location("bench_vs_torch", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks its module up there
    spec.loader.exec_module(module)
    return module


def _fake_torch_python(tmp_path: Path, median_s: float) -> Path:
    """A 'Python' that imports torch (``-c``) and answers bench_torch.py with one JSON line."""
    fake = tmp_path / "python"
    fake.write_text(
        "#!/bin/sh\n"
        '[ "$1" = "-c" ] && exit 0\n'
        f'echo \'{{"median_s": {median_s}, "foreign_cpu_frac": 0.25, "torch": "fake", "threads": 2}}\'\n'
    )
    fake.chmod(0o755)
    return fake


def test_torch_python_problems_are_one_line(tmp_path: Path) -> None:
    bench = _module()
    missing = bench.check_torch_python(None)
    absent = bench.check_torch_python(str(tmp_path / "nothing"))
    without_torch = bench.check_torch_python(sys.executable)  # the project's environment has no torch
    assert "--torch-python PATH is required" in missing
    assert "cannot be run" in absent
    assert "cannot import torch" in without_torch
    assert all("\n" not in m for m in (missing, absent, without_torch))
    assert bench.check_torch_python(str(_fake_torch_python(tmp_path, 0.1))) is None


def test_missing_torch_python_exits_with_one_line() -> None:
    done = subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True, check=False)
    assert done.returncode == 2
    assert done.stdout == ""
    assert done.stderr.count("\n") == 1 and "--torch-python PATH is required" in done.stderr


def test_row_has_each_pair_its_ratio_and_the_median() -> None:
    bench = _module()
    pairs = [(bench.Run(100.0, 0.0, 0.5), bench.Run(50.0, 0.1, 0.7)),
             (bench.Run(90.0, 0.02, 0.6), bench.Run(60.0, 0.0, 1.2))]
    row = bench.table_row("Stereo DPC train step, b8", pairs, max_foreign=0.1)
    assert row == ("| Stereo DPC train step, b8 | 100.0, 90.0 | 50.0, 60.0 | 2.00, 1.50 | **1.75×** "
                   "| 0.00, 0.02 / 0.10, 0.00 | 0.5–1.2 |")
    assert row.count("|") == bench.TABLE_HEADER.splitlines()[0].count("|")
    # A pair with a busy machine is marked and left out of the median; all loaded: said so.
    assert "| 2.00*, 1.50 | **1.50×** |" in bench.table_row("x", pairs, max_foreign=0.05)
    assert "| 2.00*, 1.50* | 1.75× (loaded) |" in bench.table_row("x", pairs, max_foreign=0.0)


def test_summary_row_takes_the_faster_pytorch_variant() -> None:
    bench = _module()
    eager = [bench.Run(16.0, 0.0, 0.1), bench.Run(15.0, 0.0, 0.1), bench.Run(15.8, 0.0, 0.1)]
    compiled = [bench.Run(14.0, 0.0, 0.1)]
    ours = [bench.Run(8.0, 0.0, 0.1), bench.Run(7.0, 0.0, 0.1), bench.Run(9.0, 0.0, 0.1)]
    row = bench.summary_row("ss-DPC-Net train step, b8", eager, compiled, ours)
    assert row == "| ss-DPC-Net train step, b8 | 15.80 | 14.00 | 8.00 | **1.75×** (compiled) |"
    assert row.count("|") == bench.SUMMARY_HEADER.splitlines()[0].count("|")
    # No compiled time: the eager one is the reference and the note stands in its cell.
    row = bench.summary_row("x", eager, [], ours, "did not compile within 110 s")
    assert row == "| x | 15.80 | did not compile within 110 s | 8.00 | **1.98×** (eager) |"


def test_configuration_names_beyond_the_defaults() -> None:
    bench = _module()
    assert bench.parse_config_name("stereo-train-32") == ("stereo", "train", 32)
    for bad in ("stereo-train", "mono-fly-8", "mono-infer-0", "rgb-infer-1", "mono-infer-x"):
        with pytest.raises(ValueError, match="VARIANT-MODE-BATCH"):
            bench.parse_config_name(bad)


@pytest.mark.slow
def test_end_to_end_against_a_stand_in(tmp_path: Path) -> None:
    fake = _fake_torch_python(tmp_path, 0.5)
    command = [sys.executable, str(SCRIPT), "--torch-python", str(fake), "--torch-bench", str(SCRIPT),
               "--only", "mono-infer-1", "--pairs", "2", "--wait-quiet", "0", "--reps", "2", "--warmup", "0",
               "--size", "32", "48"]
    done = subprocess.run(command, capture_output=True, text=True, check=False, timeout=600)
    assert done.returncode == 0, done.stderr
    row = next(line for line in done.stdout.splitlines() if line.startswith("| ss-DPC-Net inference, b1"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "500.0, 500.0"
    ours = [float(t) for t in cells[2].split(", ")]
    ratios = [float(r.rstrip("*")) for r in cells[3].split(", ")]
    assert len(ours) == 2 and all(t > 0 for t in ours)
    assert ratios == pytest.approx([500.0 / t for t in ours], rel=0.01)
    assert cells[5].startswith("0.25, 0.25 / ")
    assert cells[3].count("*") == 2 and cells[4].endswith("(loaded)")  # the stand-in reports 0.25
