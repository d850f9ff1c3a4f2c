"""JAX's persistent compilation cache for the ``dpc-jax`` command: a second run compiles nothing.

JAX compiles every jitted function afresh in each new process; for a short command that is most
of its time (docs/performance.md: ``dpc-jax evaluate`` with a cold and a warm cache). With the
persistent cache XLA's executables are kept on disk, keyed by the program, its shapes, the JAX
version and the device, and a later process with the same key loads them instead of compiling
(``benchmarks/bench_cli.py`` measures both).

:func:`use_compilation_cache` points JAX at :func:`cache_folder` through JAX's own environment
variables (``JAX_COMPILATION_CACHE_DIR``, ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS``), which
JAX reads when it is imported: it must run before that, and then holds for the whole process. The
``dpc-jax`` executable calls it first thing; library code never does (call it before importing JAX,
or set JAX's options, in your own programs).
``DPC_JAX_COMPILATION_CACHE=0`` turns it off, ``DPC_JAX_COMPILATION_CACHE=PATH`` moves it, and a
``JAX_COMPILATION_CACHE_DIR`` of your own is left as it is. The folder may be deleted at any
time; it grows by one entry per compiled program and shape (about 0.1 MB for the metrics of one
trajectory length, a few MB for a network), up to :data:`MAX_SIZE_BYTES`: beyond that JAX deletes
the least recently used entries (``JAX_COMPILATION_CACHE_MAX_SIZE``, in bytes, sets another
limit; JAX locks the folder with ``filelock`` to do this). JAX trusts what it loads from the cache,
so the folder is created readable and writable by its owner only.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

OPT_OUT = "DPC_JAX_COMPILATION_CACHE"
# Every compiled program is stored: "a second run compiles nothing" (JAX's default, 1 s, would
# leave out the programs that compile in under a second, and which ones those are depends on the
# machine and its load).
MIN_COMPILE_TIME_S = 0.0
# A bound on the folder in the user's home, which would otherwise grow with every new shape and
# JAX version: room for hundreds of compiled networks.
MAX_SIZE_BYTES = 1 << 30


def cache_folder(environ: Mapping[str, str] = os.environ) -> Path | None:
    """Where the command line keeps compiled programs, or None when ``DPC_JAX_COMPILATION_CACHE=0``.

    ``$DPC_JAX_COMPILATION_CACHE`` if set, else ``$XDG_CACHE_HOME/dpc_jax/jax``, else
    ``~/.cache/dpc_jax/jax`` (the XDG base-directory rule: a relative ``XDG_CACHE_HOME`` is ignored).
    """
    chosen = environ.get(OPT_OUT, "")
    if chosen == "0":
        return None
    if chosen:
        return Path(chosen).expanduser()
    xdg = environ.get("XDG_CACHE_HOME", "")
    base = Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache"
    return base / "dpc_jax" / "jax"


def use_compilation_cache() -> Path | None:
    """Turn JAX's persistent compilation cache on for this process (and its children): the folder used.

    Call it before JAX is imported (JAX reads the variables then). Returns None, changing nothing,
    when the cache is off, when ``JAX_COMPILATION_CACHE_DIR`` is already set (that folder is used),
    or when the folder cannot be created or written (the cache only saves time; the command runs
    without it).
    """
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return None
    folder = cache_folder()
    if folder is None:
        return None
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError:
        return None
    if not os.access(folder, os.W_OK | os.X_OK):
        return None
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(folder)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", str(MIN_COMPILE_TIME_S))
    os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(MAX_SIZE_BYTES))
    return folder
