"""Data parallelism: one train step on 4 devices equals the same step on 1 device.

JAX fixes its device count when it initialises, so the 4-device run happens in a subprocess with
``XLA_FLAGS=--xla_force_host_platform_device_count=4`` (the rest of the suite keeps 1 device).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np
import pytest
from jax.sharding import PartitionSpec

from dpc_jax.training import parallel

SCRIPT = textwrap.dedent(
    """
    import jax, numpy as np
    from jax.sharding import PartitionSpec
    from dpc_jax.training import parallel
    from dpc_jax.nn.batch import Batch
    from dpc_jax.nn.models import create_model
    from dpc_jax.training.optim import create_train_state, make_optimizer
    from dpc_jax.training.steps import make_train_step
    from dpc_jax.training.config import TrainConfig

    assert len(jax.devices()) == 4, jax.devices()
    TINY = dict(encoder_planes=(8, 16, 32), encoder_kernels=(3, 3, 3), decoder_planes=(32, 16, 8),
                mask_source_block=2, depth_scales=2, fc_planes=(16, 16))
    config = TrainConfig(method="ss_dpc", preset="small", model=TINY, image_size=(32, 48), batch_size=8,
                         learning_rate=1e-3, validation_sequences=("v",), pose_warmup_epochs=0)
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
    env["XLA_FLAGS"] = "--xla_force_host_platform_device_count=4"
    script = tmp_path / "four_devices.py"
    script.write_text(SCRIPT)
    result = subprocess.run(
        [sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=900,
        cwd=Path(__file__).resolve().parents[1],
    )
    assert result.returncode == 0, result.stdout + result.stderr
    ok = result.stdout.strip().splitlines()[-1].split()
    assert ok[0] == "OK"
    n_leaves, changed = int(ok[1]), int(ok[2])
    # Parameters, BatchNorm statistics and Adam moments all moved (the step did something).
    assert changed > n_leaves // 2
