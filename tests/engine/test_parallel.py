"""Data parallelism: one train step on 4 devices equals the same step on 1 device; two processes
(JAX's CPU collectives, coordinator on localhost) train as one process with two devices.

JAX fixes its device count when it initialises, so the multi-device runs happen in subprocesses
with ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (the rest of the suite keeps 1 device).
"""

from __future__ import annotations

import csv
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np
import pytest
from flax import nnx
from jax.sharding import PartitionSpec
from support import XLA_TEST_FLAGS

from dpc_jax.engine import parallel

SCRIPT = textwrap.dedent(
    """
    import jax, numpy as np
    from jax.sharding import PartitionSpec
    from dpc_jax.engine import parallel
    from dpc_jax.nn.batch import Batch
    from dpc_jax.nn.models import create_model
    from dpc_jax.pipelines.protocol import SMOKE
    from dpc_jax.training.optim import create_train_state, make_optimizer
    from dpc_jax.training.steps import make_train_step
    from dpc_jax.training.train_config import TrainConfig

    assert len(jax.devices()) == 4, jax.devices()
    config = TrainConfig(method="ss_dpc", preset="small", model=SMOKE["model"], image_size=(32, 48),
                         batch_size=8, learning_rate=1e-3, validation_sequences=("v",), pose_warmup_epochs=0)
    rng = np.random.default_rng(0)
    B, H, W = 8, 32, 48
    K = np.array([[30.0, 0, 24], [0, 30, 16], [0, 0, 1]], np.float32)
    batch = Batch(
        left=rng.integers(0, 256, (B, 2, H, W, 3), dtype=np.uint8),
        right=rng.integers(0, 256, (B, 2, H, W, 3), dtype=np.uint8),
        xi_vo=(rng.normal(size=(B, 6)) * [0.3, 0.05, 1.0, 0.01, 0.02, 0.01]).astype(np.float32),
        intrinsics=np.tile(K, (B, 1, 1)),
        baseline=np.full(B, 0.5, np.float32),
        weight=np.array([1, 1, 1, 1, 1, 1, 1, 0], np.float32),
        flow=rng.normal(size=(B, 2, H, W, 2)).astype(np.float32),
    )
    graphdef, initial = create_train_state(create_model("ss_dpc", config.model_config(), 0),
                                           make_optimizer(config, 10))
    initial = jax.device_get(initial)
    results = []
    for n in (1, 4):
        mesh = parallel.make_mesh(jax.devices()[:n])
        sharded = parallel.shard_batch(batch, mesh)
        assert sharded.left.sharding.spec == PartitionSpec("data")
        assert len({s.device for s in sharded.left.addressable_shards}) == n
        state = parallel.replicate(initial, mesh)
        step = make_train_step(config.loss_config(), 0, mesh)
        state, metrics = step(graphdef, state, sharded, jax.random.key(3))
        leaf = jax.tree.leaves(state)[0]
        assert leaf.sharding.is_fully_replicated and len(leaf.sharding.device_set) == n
        results.append((jax.device_get(state), jax.device_get(metrics)))
    (s1, m1), (s4, m4) = results
    for k in m1:
        np.testing.assert_allclose(m4[k], m1[k], rtol=2e-5, atol=1e-7, err_msg=k)
    changed = 0
    for (path, a), b, c in zip(jax.tree_util.tree_leaves_with_path(s1), jax.tree.leaves(s4),
                               jax.tree.leaves(initial), strict=True):
        if np.issubdtype(np.asarray(a).dtype, np.floating):
            # Adam's first step is lr·g/(|g| + ε): where |g| is near ε, float32 summation order
            # (one device vs four) moves it by a fraction of lr; a wrong reduction moves it by ~lr.
            np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-2 * config.learning_rate,
                                       err_msg=jax.tree_util.keystr(path))
            changed += not np.array_equal(a, c)
        else:
            np.testing.assert_array_equal(b, a, err_msg=jax.tree_util.keystr(path))
    print("OK", len(jax.tree.leaves(s1)), changed, float(m1["loss"]))
    """
)


def test_mesh_and_shardings_on_one_device() -> None:
    mesh = parallel.make_mesh()
    assert mesh.axis_names == ("data",) and mesh.devices.size == len(jax.devices())
    assert parallel.batch_sharding(mesh).spec == PartitionSpec("data")
    assert parallel.replicated(mesh).spec == PartitionSpec()
    assert parallel.process_slice(8) == slice(0, 8)
    tree = {"a": np.arange(6.0).reshape(3, 2), "b": None}
    out = parallel.shard_batch(tree, mesh)
    assert out["b"] is None and np.array_equal(np.asarray(out["a"]), tree["a"])
    parallel.check_batch_size(4, mesh)
    with pytest.raises(ValueError, match="not divisible"):
        parallel.check_batch_size(6, SimpleNamespace(devices=np.empty(4)))


@pytest.mark.slow
def test_step_on_four_devices_equals_one_device(tmp_path: Path) -> None:
    """Same global batch (with a padding sample): loss, gradients' effect and BatchNorm statistics agree."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "XLA_"))}
    env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count=4 {XLA_TEST_FLAGS}"
    script = tmp_path / "four_devices.py"
    script.write_text(SCRIPT)
    result = subprocess.run(
        [sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=900,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert result.returncode == 0, result.stdout + result.stderr
    ok = result.stdout.strip().splitlines()[-1].split()
    assert ok[0] == "OK"
    n_leaves, changed = int(ok[1]), int(ok[2])
    # Parameters, BatchNorm statistics and Adam moments all moved (the step did something).
    assert changed > n_leaves // 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return int(s.getsockname()[1])


@pytest.mark.slow
def test_two_processes_train_like_one_process_with_two_devices(tmp_path: Path) -> None:
    """``dpc-jax train`` as two processes of one device each (``--coordinator-address localhost:PORT
    --num-processes 2 --process-id I``, what the README tells several hosts to run) and as one
    process with two forced devices: the same global batches, so the same losses and parameters."""
    from support import TINY_SIZE, make_caches

    from dpc_jax import config as config_lib
    from dpc_jax.correction.inference import load_run
    from dpc_jax.nn.models import create_model
    from dpc_jax.pipelines.protocol import SMOKE
    from dpc_jax.training.train_config import TrainConfig

    # ss-DPC-Net, whose programs compile in about half the time of Stereo DPC's: the batch is sharded and
    # the gradients and BatchNorm statistics reduced over the data axis whatever the loss.
    cache = make_caches(tmp_path / "data", ["00", "01"], n_frames=10, flow=True)
    fields = dict(method="ss_dpc", preset="small", model=SMOKE["model"], image_size=TINY_SIZE,
                  batch_size=4, epochs=1, learning_rate=1e-3, steps_per_epoch=3, cache_root=str(cache),
                  validation_sequences=("01",), log_every=1, pose_warmup_epochs=0, frame_skip=False)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "XLA_"))}
    env["JAX_PLATFORMS"] = "cpu"
    env["XLA_FLAGS"] = XLA_TEST_FLAGS
    runs = {}
    for name, distributed in (("two_processes", True), ("one_process", False)):
        config = config_lib.from_dict(TrainConfig, {**fields, "distributed": distributed})
        config_file = tmp_path / f"{name}.py"
        config_file.write_text(f"CONFIG = {config_lib.to_dict(config)!r}\n")
        runs[name] = [sys.executable, "-m", "dpc_jax", "train", "--config", str(config_file),
                      "--workdir", str(tmp_path / name), "--no-progress", "--workers", "1"]
    port = _free_port()
    workers = [
        subprocess.Popen([*runs["two_processes"], "--coordinator-address", f"localhost:{port}",
                          "--num-processes", "2", "--process-id", str(i)],
                         env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for i in range(2)
    ]
    try:
        two_devices = f"--xla_force_host_platform_device_count=2 {XLA_TEST_FLAGS}"
        single = subprocess.run(runs["one_process"], capture_output=True, text=True, timeout=900,
                                env={**env, "XLA_FLAGS": two_devices})
        outputs = [w.communicate(timeout=900)[0] for w in workers]
    finally:
        for w in workers:
            if w.poll() is None:
                w.kill()
    assert single.returncode == 0, single.stdout + single.stderr
    for w, out in zip(workers, outputs, strict=True):
        assert w.returncode == 0, out
    # Only process 0 reports and logs: process 1 really was a second process of the run.
    assert "epoch 1:" in outputs[0] and "epoch 1:" not in outputs[1]

    def losses(name: str) -> list[float]:
        with (tmp_path / name / "metrics.csv").open(newline="") as f:
            return [float(row["train_loss"]) for row in csv.DictReader(f)]

    np.testing.assert_allclose(losses("two_processes"), losses("one_process"), rtol=1e-6)
    one, two = load_run(tmp_path / "one_process", "last"), load_run(tmp_path / "two_processes", "last")
    start = nnx.state(create_model("ss_dpc", one.config.model_config(), one.config.seed))
    moved = 0
    for (path, a), b, c in zip(jax.tree_util.tree_leaves_with_path(one.state), jax.tree.leaves(two.state),
                               jax.tree.leaves(start), strict=True):
        # The same reductions over the same two devices: equal to float rounding.
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-5, atol=1e-7,
                                   err_msg=jax.tree_util.keystr(path))
        moved += not np.array_equal(np.asarray(a), np.asarray(c))
    assert moved > len(jax.tree.leaves(start)) // 2

