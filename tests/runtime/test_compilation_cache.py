"""dpc_jax.runtime.compilation_cache: where the command line keeps compiled programs, the opt-out, and a
second ``dpc-jax evaluate`` that compiles nothing and prints the same numbers."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from support import fixture_poses

from dpc_jax.data.poses_io import read_trajectory, write_kitti_poses
from dpc_jax.eval.evaluation import evaluate
from dpc_jax.runtime import compilation_cache
from dpc_jax.runtime.compilation_cache import OPT_OUT, cache_folder, use_compilation_cache


def test_cache_folder_follows_the_variable_then_xdg_then_home(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HOME", "/home/u")
    assert cache_folder({}) == Path("/home/u/.cache/dpc_jax/jax")
    assert cache_folder({"XDG_CACHE_HOME": "/xdg"}) == Path("/xdg/dpc_jax/jax")
    assert cache_folder({"XDG_CACHE_HOME": "relative"}) == Path("/home/u/.cache/dpc_jax/jax")
    assert cache_folder({OPT_OUT: "/elsewhere", "XDG_CACHE_HOME": "/xdg"}) == Path("/elsewhere")
    assert cache_folder({OPT_OUT: "~/jit"}) == Path("/home/u/jit")
    assert cache_folder({OPT_OUT: "0", "XDG_CACHE_HOME": "/xdg"}) is None


def _jax_variables(monkeypatch: pytest.MonkeyPatch) -> None:
    """Let use_compilation_cache write JAX's variables into a copy of the environment."""
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.delenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", raising=False)
    monkeypatch.delenv("JAX_COMPILATION_CACHE_MAX_SIZE", raising=False)


def test_use_sets_jax_variables_and_a_private_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _jax_variables(monkeypatch)
    folder = tmp_path / "a" / "jax"
    monkeypatch.setenv(OPT_OUT, str(folder))
    assert use_compilation_cache() == folder
    assert os.environ["JAX_COMPILATION_CACHE_DIR"] == str(folder)
    min_time = float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"])
    assert min_time == compilation_cache.MIN_COMPILE_TIME_S
    assert int(os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"]) == compilation_cache.MAX_SIZE_BYTES
    # JAX runs what it loads from the cache: nobody else may write there.
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700


def test_use_leaves_off_a_chosen_jax_folder_and_an_unwritable_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _jax_variables(monkeypatch)
    monkeypatch.setenv(OPT_OUT, "0")
    assert use_compilation_cache() is None and "JAX_COMPILATION_CACHE_DIR" not in os.environ

    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv(OPT_OUT, str(blocker / "jax"))
    assert use_compilation_cache() is None and "JAX_COMPILATION_CACHE_DIR" not in os.environ

    monkeypatch.setenv(OPT_OUT, str(tmp_path / "ours"))
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "theirs"))
    assert use_compilation_cache() is None
    assert os.environ["JAX_COMPILATION_CACHE_DIR"] == str(tmp_path / "theirs")
    assert not (tmp_path / "ours").exists()


def _entries(folder: Path) -> dict[str, int]:
    # The compiled programs; with the size bound JAX also keeps an access-time file per entry.
    return {p.name: p.stat().st_mtime_ns for p in folder.glob("*-cache")}


@pytest.mark.slow
def test_second_evaluate_compiles_nothing_and_prints_the_same_numbers(tmp_path: Path) -> None:
    gt = fixture_poses(80, seed=3, step=2.0)  # 158 m: segment errors of 100 m exist
    est = gt.copy()
    est[:, 0, 3] += np.linspace(0.0, 2.0, gt.shape[0])
    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "est.txt", est)
    folder = tmp_path / "cache"
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    env.update({OPT_OUT: str(folder), "DPC_JAX_HUGE_PAGES": "0"})
    command = [sys.executable, "-m", "dpc_jax", "evaluate", "--gt", str(tmp_path / "gt.txt"),
               "--est", str(tmp_path / "est.txt"), "--json", "-"]

    def run() -> str:
        return subprocess.run(command, capture_output=True, text=True, env=env, check=True).stdout

    first = run()
    written = _entries(folder)
    assert any(name.startswith("jit_trajectory_metrics") for name in written), written
    # The size bound is on: JAX keeps the access times it evicts by (and needs filelock for it).
    assert any(p.name.endswith("-atime") for p in folder.iterdir())
    second = run()
    # Every compiled program is stored (MIN_COMPILE_TIME_S = 0): no new or rewritten entry means
    # the second process compiled nothing.
    assert _entries(folder) == written
    assert second == first
    # The first process compiled afresh; so does this one, without the cache.
    reference = evaluate(read_trajectory(tmp_path / "gt.txt"), {"est": read_trajectory(tmp_path / "est.txt")})
    assert json.loads(first) == json.loads(reference.to_json())
    assert json.loads(first)["estimates"]["est"]["seg_trans_pct"] is not None
