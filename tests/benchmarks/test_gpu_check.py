"""benchmarks/gpu_check.sh in its quick mode (QUICK=1), on the CPU: every step of the prepared GPU run
goes end to end, so that a moved module or option fails here rather than in a lent GPU's minutes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_quick_mode_runs_every_step_on_the_cpu(tmp_path: Path) -> None:
    # LOOP_TIMEOUT: each step's own limit (170 s on a GPU) would cut a quick step short on a loaded CPU.
    env = {**os.environ, "QUICK": "1", "OUT": str(tmp_path / "out"), "LOOP_TIMEOUT": "500",
           "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "jc"),
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    done = subprocess.run(["bash", str(ROOT / "benchmarks" / "gpu_check.sh")], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    out = tmp_path / "out"
    assert "jax" in (out / "device.txt").read_text()
    for method in ("stereo_dpc", "ss_dpc"):
        figures = json.loads((out / f"loop_{method}.json").read_text())
        assert figures, f"{method}: no figures"
        assert "| train (2 steps/epoch), samples/s |" in (out / f"loop_{method}.txt").read_text()
    torch_part = (out / "vs_torch.md").read_text()
    assert "skipped" in torch_part or "mono-infer-1" in torch_part
