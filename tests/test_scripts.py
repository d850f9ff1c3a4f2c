"""Every benchmark and experiment script still runs: what it imports of dpc_jax exists, and ``--help`` works.

The scripts import most of the library inside their functions, where a plain import of the script does
not reach: each script's source is read for every ``dpc_jax`` module and name it imports (at any depth)
and every attribute it takes of such a module, and each must resolve. A function renamed or moved in the
package fails here, not in a user's run.
"""

from __future__ import annotations

import ast
import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted([*ROOT.glob("benchmarks/*.py"), *ROOT.glob("experiments/protocols/*.py"),
                  *ROOT.glob("experiments/studies/*.py")])


def dpc_jax_uses(source: str) -> list[tuple[str, str | None]]:
    """``(module, name)`` of every ``dpc_jax`` import of ``source`` (name None: the module itself) and
    ``(module, attribute)`` of every attribute taken of a name bound to such a module."""
    tree = ast.parse(source)
    uses: list[tuple[str, str | None]] = []
    modules: dict[str, str] = {}  # local name → dpc_jax module it is bound to
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "dpc_jax":
                    uses.append((alias.name, None))
                    if alias.asname:
                        modules[alias.asname] = alias.name
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "dpc_jax":
            for alias in node.names:
                uses.append((node.module, alias.name))
                submodule = f"{node.module}.{alias.name}"
                if importlib.util.find_spec(node.module) is not None and _is_module(submodule):
                    modules[alias.asname or alias.name] = submodule
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in modules:
            uses.append((modules[node.value.id], node.attr))
    return uses


def _is_module(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:
        return False


def test_the_check_sees_imports_inside_functions_and_module_attributes() -> None:
    """The reference: a source whose uses are known."""
    source = ("import dpc_jax.eval.metrics as M\n"
              "def f():\n"
              "    from dpc_jax.pipelines import protocol as P\n"
              "    from dpc_jax.correction.corrector import correct_cache, no_such_thing\n"
              "    return P.claim_workdir, P.gone, M.m_ate\n")
    uses = dpc_jax_uses(source)
    assert ("dpc_jax.correction.corrector", "no_such_thing") in uses
    assert ("dpc_jax.pipelines.protocol", "gone") in uses and ("dpc_jax.eval.metrics", "m_ate") in uses
    assert [u for u in uses if not _resolves(*u)] == [("dpc_jax.correction.corrector", "no_such_thing"),
                                                       ("dpc_jax.pipelines.protocol", "gone")]


def _resolves(module: str, name: str | None) -> bool:
    try:
        imported = importlib.import_module(module)
    except ImportError:
        return False
    return name is None or hasattr(imported, name) or _is_module(f"{module}.{name}")


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_what_a_script_takes_of_dpc_jax_exists(script: Path) -> None:
    missing = [f"{m}.{n}" if n else m for m, n in dpc_jax_uses(script.read_text()) if not _resolves(m, n)]
    assert not missing, f"{script.relative_to(ROOT)} uses what dpc_jax no longer has: {missing}"


# Each script as ``python SCRIPT --help`` runs it (its folder first on sys.path, run as ``__main__``), one
# after another in one interpreter, which imports JAX and the library once for all of them.
HELP_ALL = """
import contextlib, io, json, os, runpy, sys, traceback
failed = []
for script in sys.argv[1:]:
    sys.argv = [script, "--help"]
    sys.path[0] = os.path.dirname(script)
    code, err = 0, ""
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as stderr:
        try:
            runpy.run_path(script, run_name="__main__")
        except SystemExit as done:
            code = 0 if done.code is None else done.code
        except BaseException:
            code, err = 1, traceback.format_exc()
    if code != 0:
        failed.append([script, code, (err or stderr.getvalue())[-400:]])
print(json.dumps(failed))
"""


def test_every_script_answers_help() -> None:
    """``python SCRIPT --help`` exits 0 for every script (argument parsing and top-level imports)."""
    scripts = [str(s) for s in SCRIPTS if s.name != "machine.py"]  # a module the benchmarks import
    done = subprocess.run([sys.executable, "-c", HELP_ALL, *scripts], capture_output=True, text=True,
                          cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    failed = json.loads(done.stdout.strip().splitlines()[-1])
    assert not failed, failed
