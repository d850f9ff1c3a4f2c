"""Training: schedule, optimizer, train/eval steps, the loop, resume, guard and bad input."""

from __future__ import annotations

import csv
import importlib
import itertools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
import pytest

from dpc_jax import config as config_lib
from dpc_jax import models as models_lib
from dpc_jax.batch import Batch
from dpc_jax.checkpoints import Checkpoints
from dpc_jax.config import ConfigError
from dpc_jax.data.cache import prepare_sequence
from dpc_jax.data.kitti import StereoSequence
from dpc_jax.models import create_model
from dpc_jax.outputs import DPCOutputs
from dpc_jax.train import (
    NonFiniteLossError,
    TrainConfig,
    create_train_state,
    learning_rate_schedule,
    make_optimizer,
    state_step,
    train,
)

# The module itself: ``from dpc_jax import train`` is the re-exported function of the same name.
train_lib = importlib.import_module("dpc_jax.train")


@pytest.mark.parametrize(("halving", "steps_per_epoch"), [(5, 7), (4, 3), (1, 1)])
def test_schedule_halves_at_each_boundary(halving: int, steps_per_epoch: int) -> None:
    schedule = learning_rate_schedule(6e-3, halving, steps_per_epoch)
    period = halving * steps_per_epoch
    assert float(schedule(0)) == pytest.approx(6e-3, rel=1e-7)
    for k in range(1, 5):
        boundary = k * period
        assert float(schedule(boundary - 1)) == pytest.approx(6e-3 / 2 ** (k - 1), rel=1e-6)
        assert float(schedule(boundary)) == pytest.approx(6e-3 / 2**k, rel=1e-6)


def _torch_adam_reference(theta, grad_fn, lrs, wd, b1=0.9, b2=0.999, eps=1e-8):
    """PyTorch ``Adam(weight_decay=wd)`` in float64 numpy: wd·θ is added to the gradient."""
    m = np.zeros_like(theta)
    v = np.zeros_like(theta)
    for t, lr in enumerate(lrs, start=1):
        g = grad_fn(theta) + wd * theta
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        m_hat, v_hat = m / (1 - b1**t), v / (1 - b2**t)
        theta = theta - lr * m_hat / (np.sqrt(v_hat) + eps)
    return theta


def test_optimizer_is_adam_with_coupled_weight_decay_and_the_schedule() -> None:
    """Steps across two halving boundaries match PyTorch's Adam(weight_decay) update rule."""
    config = TrainConfig(validation_sequences=("v",), preset="small", learning_rate=0.05,
                         lr_halving_epochs=2, weight_decay=0.3)
    steps_per_epoch, n_steps = 3, 14
    tx = make_optimizer(config, steps_per_epoch)
    target = np.array([1.0, -2.0, 0.5, 3.0])
    grad_fn = lambda th: 2.0 * (th - target) * np.array([1.0, 10.0, 0.1, 1.0])
    theta = np.array([0.3, 0.1, -1.0, 2.0])
    params = jnp.asarray(theta)
    state = tx.init(params)
    for _ in range(n_steps):
        updates, state = tx.update(jnp.asarray(grad_fn(np.asarray(params))), state, params)
        params = optax.apply_updates(params, updates)
    lrs = [0.05 * 0.5 ** (s // (2 * steps_per_epoch)) for s in range(n_steps)]
    expected = _torch_adam_reference(theta, grad_fn, lrs, 0.3)
    # The schedule evaluates the rate in float32 (0.05 → 0.05000000075): 1e-7 relative.
    np.testing.assert_allclose(np.asarray(params), expected, rtol=1e-7, atol=1e-12)
    # Decoupled decay (AdamW) or a constant rate would land elsewhere.
    assert not np.allclose(_torch_adam_reference(theta, grad_fn, [0.05] * n_steps, 0.3), expected, atol=1e-6)
    assert not np.allclose(_torch_adam_reference(theta, grad_fn, lrs, 0.0), expected, atol=1e-6)


# --------------------------------------------------------------------------- the loop

# A two-block network: compiles in seconds, enough to exercise every part of the loop.
TINY = {"encoder_planes": [4, 8], "encoder_kernels": [3, 3], "decoder_planes": [8, 4],
        "mask_source_block": 1, "depth_scales": 1, "fc_planes": [8, 8]}
SIZE = (32, 48)


def make_caches(root: Path, names: list[str], n_frames: int = 12) -> Path:
    """Prepared caches of tiny textured sequences moving 1 m/frame forward, with ground truth."""
    h, w = SIZE
    K = np.array([[0.7 * w, 0, w / 2], [0, 0.7 * w, h / 2], [0, 0, 1.0]])
    rng = np.random.default_rng(0)
    for name in names:
        texture = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 2 * n_frames + 2, 3)), (5, 5), 1.5)
        folder = root / "images" / name
        folder.mkdir(parents=True)
        paths: dict[str, list[Path]] = {"l": [], "r": []}
        for i in range(n_frames):
            for cam, shift in (("l", 0), ("r", 2)):
                path = folder / f"{cam}{i:03d}.png"
                cv2.imwrite(str(path), texture[:, 2 * i + shift:2 * i + shift + w].astype(np.uint8))
                paths[cam].append(path)
        gt = np.tile(np.eye(4), (n_frames, 1, 1))
        gt[:, 2, 3] = np.arange(n_frames)
        prior = gt.copy()
        prior[:, 0, 3] += rng.normal(0, 0.01, n_frames)
        sequence = StereoSequence(name, tuple(paths["l"]), tuple(paths["r"]), K, 0.5, SIZE,
                                  np.arange(n_frames) * 0.1, gt)
        prepare_sequence(sequence, prior, root / "cache", size=SIZE, progress=False, workers=1)
    return root / "cache"


@pytest.fixture(scope="module")
def cache_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_caches(tmp_path_factory.mktemp("data"), ["00", "01", "02"])


def tiny_config(cache_root: Path, **overrides: object) -> TrainConfig:
    fields = dict(method="stereo_dpc", preset="small", model=TINY, image_size=SIZE, batch_size=4, epochs=2,
                  learning_rate=1e-3, steps_per_epoch=3, cache_root=str(cache_root),
                  validation_sequences=("02",), log_every=1)
    fields.update(overrides)
    return config_lib.from_dict(TrainConfig, fields)


def _cheap_loss(outputs: DPCOutputs, batch: Batch) -> tuple[jax.Array, dict[str, jax.Array]]:
    value = jnp.mean(outputs.left.inv_depth) + jnp.mean(outputs.right.mask) + jnp.sum(outputs.xi_corr**2)
    return value, {"xi_norm": jnp.sum(outputs.xi_corr**2)}


def _cheap_gradient_loss(outputs: DPCOutputs, batch: Batch) -> jax.Array:
    return jnp.mean(outputs.left.inv_depth)


@pytest.fixture
def cheap_losses(monkeypatch: pytest.MonkeyPatch) -> None:
    """The loop with a loss that compiles fast (the real losses run in the slow end-to-end test)."""
    monkeypatch.setattr(train_lib, "make_loss_functions", lambda config: (_cheap_loss, _cheap_gradient_loss))


def _read_metrics(workdir: Path) -> list[dict[str, str]]:
    with (workdir / "metrics.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def test_loop_writes_checkpoints_metrics_and_refuses_other_runs(
    cache_root: Path, tmp_path: Path, cheap_losses: None
) -> None:
    config = tiny_config(cache_root)
    summary = train(config, tmp_path, progress=False, workers=0)
    assert summary["epochs"] == 2 and summary["step"] == 6
    rows = _read_metrics(tmp_path)
    assert [(r["epoch"], r["step"]) for r in rows] == [("1", "3"), ("2", "6")]
    for column in ("learning_rate", "train_loss", "train_xi_norm", "train_grad_norm", "samples_per_s",
                   "val_loss", "val_gradient_loss", "val_loop_closures", "val_prior_r_err",
                   "val_corrected_r_err"):
        assert all(r[column] != "" for r in rows), column
    assert float(rows[0]["learning_rate"]) == pytest.approx(1e-3)
    assert list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))
    ckpt = Checkpoints(tmp_path, read_only=True)
    assert ckpt.all_epochs() == [1, 2]
    assert ckpt.latest_epoch("best_gradient_loss") in (1, 2)
    assert ckpt.latest_epoch("best_loop_closures") in (1, 2)
    stored = config_lib.load_file(tmp_path / "checkpoints" / "config.json", TrainConfig)
    assert stored == config
    split = json.loads((tmp_path / "checkpoints" / "split.json").read_text())
    assert split["train"] == ["00", "01"] and split["validation"] == ["02"] and split["steps_per_epoch"] == 3
    # The optimizer step count in the checkpoint is the number of updates made.
    _, fresh = create_train_state(create_model(config.method, config.model_config(), 0),
                                  make_optimizer(config, 3))
    restored, meta = ckpt.restore(jax.tree.map(ocp.utils.to_shape_dtype_struct, fresh))
    assert state_step(restored) == 6 and meta["step"] == 6 and meta["data"]["next_epoch"] == 3
    ckpt.close()

    with pytest.raises(ConfigError, match=r"already holds a training run.*--resume"):
        train(config, tmp_path, progress=False)
    with pytest.raises(ConfigError, match=r"different config.*epochs: 2 → 3"):
        train(tiny_config(cache_root, epochs=3), tmp_path, resume=True, progress=False)
    # Resuming a finished run with its own config does no further epoch.
    again = train(config, tmp_path, resume=True, progress=False, workers=0)
    assert again["step"] == 6 and len(_read_metrics(tmp_path)) == 2


def test_non_finite_loss_stops_and_keeps_the_last_good_checkpoint(
    cache_root: Path, tmp_path: Path, cheap_losses: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = train_lib.make_train_step

    def poisoned(loss_fn: object, mesh: object = None) -> object:
        step = real(loss_fn, mesh)
        calls = itertools.count()

        def wrapped(graphdef, state, batch, key):  # the 5th update (epoch 2) yields NaN
            state, metrics = step(graphdef, state, batch, key)
            return state, {**metrics, "loss": metrics["loss"] * (jnp.nan if next(calls) == 4 else 1.0)}

        return wrapped

    monkeypatch.setattr(train_lib, "make_train_step", poisoned)
    message = r"non-finite training loss \(nan\) at epoch 2, step 5.*checkpoint \(epoch 1\) is intact"
    with pytest.raises(NonFiniteLossError, match=message):
        train(tiny_config(cache_root), tmp_path, progress=False, workers=0)
    with Checkpoints(tmp_path, read_only=True) as ckpt:
        assert ckpt.all_epochs() == [1]
    assert [r["epoch"] for r in _read_metrics(tmp_path)] == ["1"]


def test_bad_input_fails_before_any_compute(
    cache_root: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def no_compute(*args: object, **kwargs: object) -> None:
        raise AssertionError("a model was built before the input was checked")

    monkeypatch.setattr(models_lib, "create_model", no_compute)
    with pytest.raises(ConfigError, match=r"validation_sequences \['07'\] are not prepared"):
        train(tiny_config(cache_root, validation_sequences=("07",)), tmp_path / "a", progress=False)
    with pytest.raises(ConfigError, match="images are 32x48, the model expects 64x96"):
        train(tiny_config(cache_root, image_size=(64, 96)), tmp_path / "b", progress=False)
    with pytest.raises(ConfigError, match="not a directory"):
        train(tiny_config(tmp_path / "nowhere"), tmp_path / "c", progress=False)
    other = tmp_path / "e" / "checkpoints"
    config_lib.save_json(other / "config.json", tiny_config(cache_root, seed=5))
    with pytest.raises(ConfigError, match="seed: 5 → 0"):
        train(tiny_config(cache_root), tmp_path / "e", resume=True, progress=False)
    stored = tmp_path / "f" / "checkpoints"
    config_lib.save_json(stored / "config.json", tiny_config(cache_root))
    split = train_lib.open_data(tiny_config(cache_root), workers=0).split
    config_lib.save_json(stored / "split.json", {**split, "train_samples": 1})
    with pytest.raises(ConfigError, match=r"cannot resume: train_samples: 1 → 42$"):
        train(tiny_config(cache_root), tmp_path / "f", resume=True, progress=False)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def _subprocess_env(tmp_path: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "XLA_"))}
    # The resumed process finds the first one's programs in the persistent compilation cache.
    env["JAX_COMPILATION_CACHE_DIR"] = str(tmp_path / "jax-cache")
    env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    return env


@pytest.mark.slow
def test_sigkill_mid_epoch_then_resume(cache_root: Path, tmp_path: Path) -> None:
    """The real Stereo DPC loss end to end; a SIGKILL in epoch 2 loses at most epoch 2."""
    config = tiny_config(cache_root, epochs=3, steps_per_epoch=None)
    config_file = tmp_path / "tiny.py"
    config_file.write_text(f"CONFIG = {config_lib.to_dict(config)!r}\n")
    workdir = tmp_path / "run"
    command = [sys.executable, "-m", "dpc_jax", "train", "--config", str(config_file), "--workdir",
               str(workdir), "--no-progress", "--workers", "1"]
    env = _subprocess_env(tmp_path)
    log = tmp_path / "first.log"
    with log.open("w") as out:
        process = subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 900
        while not (workdir / "checkpoints" / "epochs" / "1").is_dir():
            assert process.poll() is None, log.read_text()
            assert time.monotonic() < deadline, "epoch 1 did not finish in time"
            time.sleep(0.02)
        process.send_signal(signal.SIGKILL)
        process.wait()
    with Checkpoints(workdir, read_only=True) as ckpt:
        assert ckpt.all_epochs() == [1], "the kill should land in epoch 2 (10 steps)"
    before = _read_metrics(workdir)
    assert before[0]["epoch"] == "1"

    result = subprocess.run([*command, "--resume"], env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads(result.stdout[result.stdout.index("{"):])
    assert summary["epochs"] == 3 and summary["step"] == 30
    with Checkpoints(workdir, read_only=True) as ckpt:
        assert ckpt.all_epochs() == [1, 2, 3]
    after = _read_metrics(workdir)
    assert [r["epoch"] for r in after] == ["1", "2", "3"]
    assert after[0] == before[0]  # epoch 1 was not redone
    assert all(np.isfinite(float(r["val_gradient_loss"])) for r in after)
