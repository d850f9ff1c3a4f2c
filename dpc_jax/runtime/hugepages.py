"""Transparent huge pages for XLA's CPU buffers: glibc's ``malloc.hugetlb`` tunable.

XLA's CPU runtime allocates the temporary buffers of a compiled function afresh on every call,
and glibc serves the large ones with new ``mmap`` regions. A training step of ss-DPC-Net at batch
8, 240×376, therefore touches about 470 MB of fresh memory in 4 KiB pages: some 120 000 page
faults per step, and a 4 KiB TLB for the large strided transposes of the backward pass. With
``GLIBC_TUNABLES=glibc.malloc.hugetlb=1`` (glibc ≥ 2.35) malloc marks its memory for transparent
huge pages (``madvise``), the faults drop to a few hundred, and the step takes less time
(``benchmarks/bench_models.py`` prints the state and the figures; docs/performance.md keeps them).

glibc reads its tunables once, when the process starts, so ``reexec_with_huge_pages`` restarts the
interpreter with the tunable added. The experiments and the benchmarks call it first thing;
``dpc-jax`` only for the subcommands where it pays (their ``HUGE_PAGES``), because the restart is a
second interpreter start. Measured as whole processes (docs/performance.md), huge pages speed up
``correct``, ``synth`` and ``vo``, and ``train`` and ``demo``, whose time goes into training steps;
``evaluate`` and ``prepare`` gain nothing, so they run without the restart, the others with it.
``DPC_JAX_HUGE_PAGES=0`` turns it off everywhere. It does nothing where it cannot help: not Linux,
not glibc, glibc older than 2.35, transparent huge pages disabled system-wide, or the tunable
already set. Library users who want the speed-up in their own
programs export the variable themselves.
"""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path

TUNABLE = "glibc.malloc.hugetlb"
OPT_OUT = "DPC_JAX_HUGE_PAGES"
_THP_SETTING = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def huge_pages_requested() -> bool:
    """Whether this process was started with the huge-page malloc tunable."""
    return TUNABLE in os.environ.get("GLIBC_TUNABLES", "")


def _glibc_supports_tunable() -> bool:
    name, version = platform.libc_ver()
    if name != "glibc":
        return False
    try:
        major, minor = (int(part) for part in version.split(".")[:2])
    except ValueError:
        return False
    return (major, minor) >= (2, 35)


def _thp_available() -> bool:
    try:
        return "[never]" not in _THP_SETTING.read_text()
    except OSError:
        return False


def reexec_with_huge_pages() -> None:
    """Replace this process by the same command with ``glibc.malloc.hugetlb=1`` set, if useful.

    Call it before any work (the command line is run again from the start). Returns without
    doing anything when the tunable is already set, when ``DPC_JAX_HUGE_PAGES=0``, or when the
    platform cannot use it (see the module docstring).
    """
    if os.environ.get(OPT_OUT, "1") == "0" or huge_pages_requested():
        return
    if not sys.platform.startswith("linux") or not sys.executable:
        return
    if not (_glibc_supports_tunable() and _thp_available()):
        return
    env = dict(os.environ)
    env["GLIBC_TUNABLES"] = ":".join(filter(None, [env.get("GLIBC_TUNABLES"), f"{TUNABLE}=1"]))
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)
