"""What a figure was measured with: the machine (the CPU and the accelerator JAX sees), the commit of the
checkout, the date, the Python version and the library versions, recorded beside every finished stage
or cell so that a rerun may reuse figures of another machine or commit and still say which."""

from __future__ import annotations

import datetime
import functools
import platform
import subprocess
import sys
from pathlib import Path

from dpc_jax.report.pages import commit
from dpc_jax.runtime.machine import this_cpu
from dpc_jax.runtime.versions import versions_line

# Asked in a process of its own: a process that starts JAX's GPU backend keeps most of the GPU's memory,
# which the measured processes (or the script's own training) would then lack.
_DEVICE = "import jax; d = jax.devices()[0]; print(d.platform, d.device_kind)"


@functools.cache
def machine() -> str:
    """The CPU (``dpc_jax.runtime.machine.this_cpu``) and, when JAX runs on another device, its kind:
    ``"AMD EPYC (family 25, model 17, AVX-512), 2 CPUs, NVIDIA H100 80GB HBM3"``. Asked once per process
    (a Python process of its own, which starts JAX: more than a second)."""
    found = subprocess.run([sys.executable, "-c", _DEVICE], capture_output=True, text=True, check=False)
    platform_name, _, kind = found.stdout.strip().partition(" ")
    return this_cpu() + ("" if platform_name in ("cpu", "") else f", {kind}")


def stamp() -> dict[str, str]:
    """``{"machine", "commit", "date", "python", "libraries"}`` of this process: the commit of the checkout
    the package runs from (``git describe --dirty``; ``unknown`` when it is installed outside one), the
    date in UTC, and ``dpc_jax.runtime.versions.versions_line``."""
    return {"machine": machine(), "commit": commit(Path(__file__).parent),
            "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d"),
            "python": platform.python_version(), "libraries": versions_line()}
