"""The lock (requirements/*.txt, written by ``bash .ci/lock``) holds what pyproject.toml asks for.

A dependency added to or narrowed in pyproject.toml without ``bash .ci/lock`` would make the README's
install and CI install something else than the package declares (or fail on a hash); this catches it
before CI does. The reference is ``packaging``'s reading of the ranges and markers (PEP 440, PEP 508).
"""

from __future__ import annotations

import importlib.util
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
# The lock's reader lives with the scripts that make and check the lock (.ci/), not in the package.
_spec = importlib.util.spec_from_file_location("lockfile", ROOT / ".ci" / "lockfile.py")
assert _spec is not None and _spec.loader is not None
lockfile = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(lockfile)
pins = lockfile.pins
def declared() -> tuple[list[Requirement], list[Requirement]]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    return ([Requirement(r) for r in project["dependencies"]],
            [Requirement(r) for r in project["optional-dependencies"]["test"]])


@pytest.mark.parametrize("lock", ["run", "test"])
def test_every_declared_dependency_is_pinned_within_its_range(lock: str) -> None:
    runtime, test_extra = declared()
    pinned = pins(ROOT / "requirements" / f"{lock}.txt")
    for requirement in runtime + (test_extra if lock == "test" else []):
        name = canonicalize_name(requirement.name)
        assert name in pinned, f"{requirement.name} is not in requirements/{lock}.txt: run bash .ci/lock"
        assert requirement.specifier.contains(pinned[name], prereleases=True), (
            f"requirements/{lock}.txt pins {name}=={pinned[name]}, outside {requirement.specifier}: "
            "run bash .ci/lock")


def test_the_two_locks_agree_and_hold_hashes() -> None:
    run, test = pins(ROOT / "requirements" / "run.txt"), pins(ROOT / "requirements" / "test.txt")
    assert run and {name: test.get(name) for name in run} == run
    for lock in ("run", "test"):
        text = (ROOT / "requirements" / f"{lock}.txt").read_text(encoding="utf-8")
        assert text.count("==") <= text.count("--hash=sha256:"), f"a pin of {lock}.txt has no hash"
