"""Reading the lock (requirements/*.txt, written by .ci/lock), for .ci/latest and tests/test_lock.py.

    python .ci/lockfile.py LOCK RESOLVED                        # what moved from LOCK to RESOLVED
    python .ci/lockfile.py --record MODE OUTCOME LOCK RESOLVED  # also into docs/dependencies.md

Pins are compared for this interpreter (their markers evaluated), by canonical name.
"""

from __future__ import annotations

import datetime
import re
import sys
from pathlib import Path

from packaging.markers import Marker
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
# "name==version ; marker \" at the start of a line; hashes and comments follow on their own lines.
PIN = re.compile(r"^([A-Za-z0-9._-]+)==([^\s;\\]+)\s*(?:;\s*([^\\]+?))?\s*\\?$")


def pins(lock: Path) -> dict[str, str]:
    """``{canonical name: version}`` of the pins of ``lock`` whose marker holds on this interpreter."""
    found: dict[str, str] = {}
    for line in lock.read_text(encoding="utf-8").splitlines():
        match = PIN.match(line)
        if match and (match[3] is None or Marker(match[3]).evaluate()):
            found[canonicalize_name(match[1])] = match[2]
    return found


def moved(lock: Path, resolved: Path) -> list[str]:
    """``"name 1.0 → 1.1"`` for each package whose version differs (or that only one side has)."""
    before, after = pins(lock), pins(resolved)
    return [f"{name} {before.get(name, '(not in the lock)')} → {after.get(name, '(not installed)')}"
            for name in sorted(before.keys() | after.keys()) if before.get(name) != after.get(name)]


def main(argv: list[str]) -> int:
    mode, outcome = "", ""
    if argv[:1] == ["--record"]:
        mode, outcome, *argv = argv[1:]
    lock, resolved = (Path(a) for a in argv)
    text = ("\n".join(f"* {line}" for line in moved(lock, resolved))
            or "* nothing: the lock holds the same versions")
    print(f"moved against {lock}:\n{text}")
    if mode:
        # Imported here: the package is installed in the environment .ci/latest made, not necessarily in
        # the one that reads pins for the tests.
        from dpc_jax.report.pages import commit, replace_block
        from dpc_jax.runtime.machine import this_cpu
        from dpc_jax.runtime.versions import versions_line

        when = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d")
        block = (f"Written by `bash .ci/latest{' --oldest' if mode == 'oldest' else ''} --record` at commit "
                 f"{commit(ROOT)}, {when}, on {this_cpu()}, with {versions_line()}.\n\n"
                 f"The checks (ruff, lint-imports, {'' if mode == 'oldest' else 'mypy, '}the test command): "
                 f"**{outcome}**.\n\n"
                 f"What moved against the lock:\n\n{text}")
        replace_block(ROOT / "docs" / "dependencies.md", mode, block)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
