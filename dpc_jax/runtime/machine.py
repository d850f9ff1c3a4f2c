"""The CPU a measurement ran on, in the one line every benchmark prints in its header and every study
records with its figures.

Speed ratios against PyTorch differ by CPU generation as much as by code (``docs/performance.md``
records figures from more than one machine), and "x86_64" or a bare "AMD EPYC" does not tell
them apart: the description adds the family and model numbers and the widest vector instruction
set, read from ``/proc/cpuinfo``.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

CPUINFO = Path("/proc/cpuinfo")

# Widest first: the first flag the CPU has names its vector unit.
VECTOR_FLAGS = (("avx512f", "AVX-512"), ("avx2", "AVX2"), ("avx", "AVX"), ("sve", "SVE"), ("asimd", "NEON"))


def cpu_description(cpuinfo: str, n_cpus: int | None, machine: str) -> str:
    """``"AMD EPYC (family 25, model 17, AVX-512), 2 CPUs"`` from the text of ``/proc/cpuinfo``
    (its first processor's block), the CPU count and ``platform.machine()``; fields that the text
    lacks are left out, and an empty text gives ``"x86_64, 2 CPUs"``."""
    fields: dict[str, str] = {}
    for line in cpuinfo.split("\n\n", 1)[0].splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields.setdefault(key.strip().lower(), value.strip())
    name = fields.get("model name") or machine or "unknown CPU"
    numbers = ("cpu family", "model")
    details = [f"{key.removeprefix('cpu ')} {fields[key]}" for key in numbers if fields.get(key)]
    flags = set((fields.get("flags") or fields.get("features") or "").split())
    details += [label for flag, label in VECTOR_FLAGS if flag in flags][:1]
    described = f"{name} ({', '.join(details)})" if details else name
    return f"{described}, {n_cpus or '?'} CPUs"


def this_cpu() -> str:
    """:func:`cpu_description` of the machine running this process."""
    try:
        cpuinfo = CPUINFO.read_text()
    except OSError:  # not Linux: the description falls back to the architecture
        cpuinfo = ""
    return cpu_description(cpuinfo, os.cpu_count(), platform.machine())
