"""The benchmarks that read the real data: without it, one line naming the option and what was expected,
exit status 1, no traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("script", "option", "needle"), [
    ("bench_vo", "--root", "raw drive folder not found"),
    ("bench_bag", "--root", "raw drive folder not found"),
    ("bench_metrics", "--mat", "no such file"),
    ("bench_cli", "--mat", "no such file"),
])
def test_missing_data_is_one_line(script: str, option: str, needle: str, tmp_path: Path) -> None:
    missing = tmp_path / "missing"
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / f"{script}.py"), option, str(missing)],
                          capture_output=True, text=True, timeout=120)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) == 1, done.stderr
    assert lines[0].startswith(f"{script}: error: {option} {missing}") and needle in lines[0], lines[0]
    assert done.stdout == ""
