"""Test-wide settings: float64 is enabled so references can be compared to 1e-9 and better, and the
command line's persistent compilation cache is off.

Library code is dtype-preserving, so float32 paths are still exercised by passing float32 inputs.

The real KITTI excerpt (``kitti-raw/``, ``kitti-libviso2/``) is read from ``DATA``: the folder named
by ``DPC_JAX_DATA``, else ``../shared/data`` beside the checkout. A clone without it still runs every
other test: a test that stops on a missing file under ``DATA`` is reported as skipped, with one
reason saying where to put the data. In CI (``CI`` set, as every CI service does) the data must be
there, and such a test fails instead; ``.ci/run`` also fails on any skip with that reason.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from collections import Counter
from collections.abc import Generator
from pathlib import Path
from types import ModuleType

from support import XLA_TEST_FLAGS

# Set before JAX starts, and inherited by the processes the tests start (support.XLA_TEST_FLAGS says why).
os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {XLA_TEST_FLAGS}".strip()

import jax
import pytest

from dpc_jax.runtime.compilation_cache import OPT_OUT

# The `dpc-jax` processes the tests start would keep their compiled programs in the user's cache
# folder: the tests leave it alone (those of the cache itself choose a temporary folder).
os.environ[OPT_OUT] = "0"

jax.config.update("jax_enable_x64", True)

SHARED = Path(__file__).resolve().parents[2] / "shared"
DATA = Path(os.environ["DPC_JAX_DATA"]).resolve() if os.environ.get("DPC_JAX_DATA") else SHARED / "data"
"""The folder holding the real data: ``kitti-raw/`` and ``kitti-libviso2/``."""

MISSING_DATA = (f"real KITTI data not found at {DATA}: put the excerpt's data folder (kitti-raw/, "
                "kitti-libviso2/) at ../shared/data beside the checkout, or set DPC_JAX_DATA=DIR")
"""The reason given for every test skipped for want of the real data (``.ci/run`` looks for it)."""

_IN_CI = os.environ.get("CI", "").lower() not in ("", "0", "false", "no")


def _data_present() -> bool:
    return (DATA / "kitti-raw").is_dir() and (DATA / "kitti-libviso2").is_dir()


def _about_missing_data(error: BaseException) -> bool:
    """Whether ``error`` (or an error it was raised from) names a path under the missing ``DATA``."""
    seen: set[int] = set()
    current: BaseException | None = error
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if str(DATA) in str(current) or any(str(DATA) in str(arg) for arg in current.args):
            return True
        current = current.__cause__ or current.__context__
    return False


def _skip_for_missing_data() -> Generator[None, object, object]:
    try:
        return (yield)
    except Exception as error:
        if _IN_CI or _data_present() or not _about_missing_data(error):
            raise
        pytest.skip(MISSING_DATA)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_setup(item: pytest.Item) -> Generator[None, object, object]:
    """A fixture that reads the real data (a cache of the excerpt, say) skips the tests using it."""
    return (yield from _skip_for_missing_data())


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Generator[None, object, object]:
    return (yield from _skip_for_missing_data())


def pytest_sessionstart(session: pytest.Session) -> None:
    if _IN_CI and not _data_present():
        raise pytest.UsageError(f"CI is set, but {MISSING_DATA.split(': ', 1)[0]}; CI must run every test")


SLOW_WEIGHT = 20.0
"""What one ``slow`` test weighs in the files' order, against 0.5 for any other test (about their seconds)."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The heaviest files first: ``-n auto`` gives each worker a file at a time in this order (pyproject's
    ``--no-loadscope-reorder`` keeps it; xdist would order by the number of tests, which sent the long
    end-to-end files, of one or two tests each, last, and one worker waited for the other). A file's weight:
    its ``slow`` tests at :data:`SLOW_WEIGHT`, the others at 0.5; the sort is stable, so a file's tests
    keep their order."""
    weight: Counter[Path] = Counter()
    for item in items:
        weight[item.path] += SLOW_WEIGHT if item.get_closest_marker("slow") else 0.5
    items.sort(key=lambda item: -weight[item.path])


def load_script(path: Path) -> ModuleType:
    """An experiment script as a module (registered in ``sys.modules``: its dataclasses look their module
    up there)."""
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
