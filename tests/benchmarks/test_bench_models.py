"""benchmarks/bench_models.py: every row of its table runs (inference, the training breakdown and the
library's own train step) at a tiny size, with the --smoke network; no timing is asserted."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest
from support import XLA_TEST_FLAGS

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_every_row_runs_and_reports_a_time() -> None:
    command = [sys.executable, str(ROOT / "benchmarks" / "bench_models.py"), "--preset", "small",
               "--height", "32", "--width", "48", "--methods", "ss_dpc", "--infer-batches", "1",
               "--train-batches", "2", "--repeats", "1", "--breakdown", "--smoke-network"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300,
                            env={"PATH": "/usr/bin:/bin", "DPC_JAX_HUGE_PAGES": "0",
                                 "XLA_FLAGS": XLA_TEST_FLAGS})
    assert result.returncode == 0, result.stderr[-2000:]
    rows = [line.split("|") for line in result.stdout.splitlines() if line.startswith("| ss_dpc")]
    assert [cells[2].strip() for cells in rows] == [
        "inference (eval)", "forward (train mode)", "loss fwd (fixed outputs)",
        "loss fwd+bwd (fixed outputs)", "forward+loss+backward", "train step (fwd+loss+bwd+Adam)"]
    assert all(math.isfinite(float(cells[4])) and float(cells[4]) > 0 for cells in rows)
