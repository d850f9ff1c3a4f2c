"""The library versions a figure was measured with, in the one line that ``dpc-jax --version`` prints,
every results page's stamp records and every performance row carries.

A figure depends on more than the commit: a new XLA compiles other code (jax, jaxlib), a new OpenCV
gives other depth, flow and features (our VO's prior and the acceptance test's Δ), and numpy and flax
take part in every step. Read from the installed distributions' metadata, so that asking never imports
JAX (``dpc-jax --version`` answers at once).
"""

from __future__ import annotations

import platform
from importlib import metadata

# (name shown, distributions that provide it: the first installed one counts). OpenCV ships under four
# names; the lock installs the headless one.
LIBRARIES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("jax", ("jax",)),
    ("jaxlib", ("jaxlib",)),
    ("flax", ("flax",)),
    ("numpy", ("numpy",)),
    ("opencv", ("opencv-python-headless", "opencv-python", "opencv-contrib-python-headless",
                "opencv-contrib-python")),
)


def library_versions() -> dict[str, str]:
    """``{"python": "3.11.7", "jax": "0.10.2", …, "opencv": "5.1.0.95"}``; ``"not installed"`` for a
    library none of whose distributions is installed."""
    found = {"python": platform.python_version()}
    for name, distributions in LIBRARIES:
        found[name] = "not installed"
        for distribution in distributions:
            try:
                found[name] = metadata.version(distribution)
                break
            except metadata.PackageNotFoundError:
                continue
    return found


def versions_line() -> str:
    """``"Python 3.11.7, jax 0.10.2, jaxlib 0.10.2, flax 0.12.8, numpy 2.4.6, opencv 5.1.0.95"``."""
    return ", ".join(f"{'Python' if name == 'python' else name} {version}"
                     for name, version in library_versions().items())
