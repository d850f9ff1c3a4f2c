"""What a command costs, measured from outside its process: wall and CPU time (``os.wait4``), the kernel's
peak resident memory, the peak of its anonymous memory (``/proc/PID/status`` sampled every 50 ms: what
the process allocated, without the file pages it mapped or wrote, which are the page cache's) and the
CPU time the rest of the machine used meanwhile (its load)."""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dpc_jax.experiments.records import Records

SAMPLE_S = 0.05


@dataclasses.dataclass
class Measured:
    """What one process (or a list of them, added up) cost: seconds and MB (10⁶ bytes)."""

    wall_s: float = 0.0
    cpu_s: float = 0.0
    peak_rss_mb: float = 0.0  # the kernel's high-water mark, file pages included
    peak_anon_mb: float = 0.0  # sampled peak of RssAnon: the process's own allocations
    others_cpu_s: float = 0.0  # CPU time the rest of the machine used meanwhile (its load)

    def add(self, other: Measured) -> Measured:
        """Both processes, one after the other: times add up, peaks are the larger (the load is not
        summed: it is a figure of one process's time)."""
        return Measured(
            self.wall_s + other.wall_s,
            self.cpu_s + other.cpu_s,
            max(self.peak_rss_mb, other.peak_rss_mb),
            max(self.peak_anon_mb, other.peak_anon_mb),
        )


def _anon_mb(pid: int) -> float | None:
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    match = re.search(r"^RssAnon:\s+(\d+) kB", text, re.MULTILINE)
    return None if match is None else int(match.group(1)) / 1000


def _busy_cpu_s() -> float:
    """CPU seconds the whole machine has spent busy since boot (``/proc/stat``), 0 where unknown."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    except OSError:
        return 0.0
    user, nice, system, _idle, _iowait, irq, softirq, steal = (int(v) for v in fields[:8])
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def measure(command: Sequence[str], log: Path, env: dict[str, str] | None = None) -> Measured:
    """Run ``command`` (its output into ``log``, ``env`` added to this process's environment) and measure
    it; ``RuntimeError`` naming the log and its last line when it fails."""
    peak = [0.0]
    with log.open("w") as out:
        start, busy = time.perf_counter(), _busy_cpu_s()
        process = subprocess.Popen(list(command), stdout=out, stderr=subprocess.STDOUT,
                                   env={**os.environ, **(env or {})})
        done = threading.Event()

        def sample() -> None:
            while not done.wait(SAMPLE_S):
                value = _anon_mb(process.pid)
                if value is not None:
                    peak[0] = max(peak[0], value)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        try:
            _, status, usage = os.wait4(process.pid, 0)
        except BaseException:
            process.kill()
            process.wait()
            raise
        finally:
            done.set()
            sampler.join()
        wall, busy = time.perf_counter() - start, _busy_cpu_s() - busy
    process.returncode = os.waitstatus_to_exitcode(status)
    if process.returncode != 0:
        tail = log.read_text(errors="replace").strip().splitlines()[-1:] or ["(no output)"]
        raise RuntimeError(f"{' '.join(command[:3])} ... failed (exit {process.returncode}; {log}): "
                           f"{tail[0]}")
    cpu = usage.ru_utime + usage.ru_stime
    return Measured(wall, cpu, usage.ru_maxrss / 1000, peak[0], max(0.0, busy - cpu))


def folder_bytes(path: Path) -> int:
    """Bytes of the regular files under ``path`` (their sizes, as a user's disk fills)."""
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink())


class Stages:
    """Measured stages of a study under ``workdir``: each runs its commands once, its record (its settings
    as ``key``, what it cost, its facts, the ``stamp``) kept in ``WORKDIR/stages/NAME.json`` and reused
    while its settings hold; the commands' output goes to ``WORKDIR/logs/``."""

    def __init__(self, workdir: Path, stamp: dict[str, str]) -> None:
        self.workdir, self.logs = workdir, workdir / "logs"
        self.records = Records(workdir / "stages", stamp)

    def run(self, name: str, key: Any, commands: Sequence[Sequence[str]], **facts: Any) -> dict[str, Any]:
        """The stage's record: its commands run one after the other and measured (:func:`measure`), with
        ``facts`` (a callable one read after the run), unless it is recorded with ``key``."""
        record = self.records.done(name, key)
        if record is None:
            self.logs.mkdir(parents=True, exist_ok=True)
            measured = Measured()
            for k, command in enumerate(commands):
                measured = measured.add(measure(command, self.logs / f"{name}{f'_{k}' if k else ''}.log"))
            facts = {k: v() if callable(v) else v for k, v in facts.items()}  # read once the stage ran
            record = self.records.write(name, {"key": key, **dataclasses.asdict(measured), **facts})
        return record
