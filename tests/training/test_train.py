"""Training: schedule, optimizer, train/eval steps, the loop, resume, guard and bad input."""

from __future__ import annotations

import csv
import dataclasses
import itertools
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
import pytest
from support import XLA_TEST_FLAGS, cheap_loss, make_caches, se3_logs, tiny_config, train_loss

from dpc_jax import config as config_lib
from dpc_jax.config import ConfigError
from dpc_jax.nn import models as models_lib
from dpc_jax.nn.models import create_model
from dpc_jax.training import loop as train_lib
from dpc_jax.training.checkpoints import Checkpoints
from dpc_jax.training.loop import train
from dpc_jax.training.optim import create_train_state, learning_rate_schedule, make_optimizer
from dpc_jax.training.steps import NonFiniteLossError, make_train_step
from dpc_jax.training.train_config import TrainConfig
from dpc_jax.training.train_data import open_data


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
                         lr_halving_epochs=2, weight_decay=0.3, pose_warmup_epochs=0)
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


def test_equal_settings_give_one_optimizer_so_runs_share_their_compiled_step() -> None:
    """The train state's graph definition holds the optimizer: equal settings give the same object, so
    two runs' definitions compare equal (the jitted step finds its program); other settings do not."""
    from dpc_jax.pipelines.protocol import SMOKE

    config = TrainConfig(method="stereo_dpc", preset="small", model=SMOKE["model"],
                         validation_sequences=("v",))
    tx = make_optimizer(config, 3)
    assert make_optimizer(config_lib.from_dict(TrainConfig, config_lib.to_dict(config)), 3) is tx
    assert make_optimizer(config, 4) is not tx
    assert make_optimizer(dataclasses.replace(config, learning_rate=2e-4), 3) is not tx
    definitions = [create_train_state(create_model("stereo_dpc", config.model_config(), seed), tx)[0]
                   for seed in (0, 1)]
    assert definitions[0] == definitions[1]
    assert create_train_state(create_model("stereo_dpc", config.model_config(), 0), make_optimizer(
        config, 4))[0] != definitions[0]


def _adam_tree_run(config: TrainConfig, steps_per_epoch: int, n_steps: int) -> tuple[dict, dict]:
    """``n_steps`` of ``make_optimizer`` on a pose-head leaf and another leaf (same quadratic)."""
    tx = make_optimizer(config, steps_per_epoch)
    theta = {"fc_out": jnp.asarray([0.3, -1.0]), "left_branch": jnp.asarray([0.3, -1.0])}
    target = jnp.asarray([1.0, 2.0])
    state = tx.init(theta)
    history = []
    for _ in range(n_steps):
        grads = jax.tree.map(lambda x: 2.0 * (x - target), theta)
        updates, state = tx.update(grads, state, theta)
        theta = optax.apply_updates(theta, updates)
        history.append(jax.tree.map(np.asarray, theta))
    return history[-1], history


def test_pose_warmup_masks_the_pose_head_and_then_starts_adam_afresh() -> None:
    config = TrainConfig(validation_sequences=("v",), preset="small", learning_rate=0.05, lr_halving_epochs=1,
                         weight_decay=0.0, pose_warmup_epochs=1, pose_warmup_steps=1)
    warmup = config.warmup_steps(3)
    assert warmup == 4
    # The supervised loss sees only ξ_corr: holding it at 0 would leave nothing to learn.
    assert dataclasses.replace(config, supervision="supervised").warmup_steps(3) == 0
    _, history = _adam_tree_run(config, 3, 6)
    start = np.array([0.3, -1.0])
    for k in range(warmup):  # no pose update while warming up, the rest trains
        np.testing.assert_array_equal(history[k]["fc_out"], start)
        assert not np.allclose(history[k]["left_branch"], start)
    # The pose head's first two updates are a fresh Adam's (steps of lr·sign(g) first), at the rates of
    # global steps 4 and 5 (halved every 3 steps: 0.025).
    lrs = [0.05 * 0.5 ** (s // 3) for s in (4, 5)]
    expected = _torch_adam_reference(start, lambda th: 2.0 * (th - np.array([1.0, 2.0])), lrs, 0.0)
    np.testing.assert_allclose(history[-1]["fc_out"], expected, rtol=1e-6)
    np.testing.assert_allclose(history[warmup]["fc_out"], start + lrs[0], rtol=1e-6)


def test_a_warmup_as_long_as_the_run_is_refused_by_train_and_warned_by_the_library(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``epochs <= pose_warmup_epochs``: the loss sees ξ_corr = 0 in every step, so the pose head keeps its
    initialisation (the warm-up's mask, checked above). ``dpc-jax train`` refuses such a config in one line
    naming the epochs it needs, before JAX; ``train`` warns with the same words."""
    from dpc_jax._io import InputWarning
    from dpc_jax.cli import main

    needs = "epochs 2 <= pose_warmup_epochs 2: the loss sees ξ_corr = 0 in every epoch"
    problem = TrainConfig(epochs=2, pose_warmup_epochs=2, validation_sequences=("v",)).pose_training_problem()
    assert problem.startswith(needs) and "give epochs >= 3" in problem
    for fields in ({"epochs": 2}, {"epochs": 1, "pose_warmup_epochs": 0},
                   {"epochs": 1, "supervision": "supervised"}):
        assert TrainConfig(validation_sequences=("v",), **fields).pose_training_problem() is None
    config = tmp_path / "config.py"
    config.write_text(f"CONFIG = {{'epochs': 1, 'cache_root': {str(tmp_path / 'none')!r}, "
                      "'validation_sequences': ('05',)}\n")
    assert main(["train", "--config", str(config), "--workdir", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--config {config}: epochs 1 <= pose_warmup_epochs 1" in err, err
    assert "give epochs >= 2" in err and not (tmp_path / "run").exists()
    with pytest.warns(InputWarning, match="give epochs >= 2"), pytest.raises(ConfigError):
        train(TrainConfig(epochs=1, cache_root=str(tmp_path / "none"), validation_sequences=("05",)),
              tmp_path / "run", progress=False)


def test_pose_lr_multiplier_scales_only_the_pose_head() -> None:
    base = dict(validation_sequences=("v",), preset="small", learning_rate=0.01, weight_decay=0.0,
                pose_warmup_epochs=0)
    plain, _ = _adam_tree_run(TrainConfig(**base), 10, 3)
    scaled, _ = _adam_tree_run(TrainConfig(**base, pose_lr_multiplier=0.25), 10, 3)
    start = np.array([0.3, -1.0])
    np.testing.assert_allclose(scaled["left_branch"], plain["left_branch"], rtol=1e-7)
    # Adam's step is invariant to the gradient's scale: a quarter of the rate is a quarter of the step
    # (three nearly equal steps here, all towards the target).
    np.testing.assert_allclose(scaled["fc_out"] - start, 0.25 * (plain["fc_out"] - start), rtol=2e-3)


# --------------------------------------------------------------------------- the loop

@pytest.fixture(scope="module")
def cache_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_caches(tmp_path_factory.mktemp("data"), ["00", "01", "02"])


@pytest.fixture
def cheap_losses() -> Iterator[None]:
    """The train step with a loss that compiles fast (validation keeps the real losses)."""
    with train_loss(cheap_loss):
        yield


def test_train_step_warmup_holds_the_correction_at_zero(cache_root: Path, cheap_losses: None) -> None:
    from dpc_jax.data.pipeline import TrainLoader

    config = tiny_config(cache_root, pose_warmup_epochs=0, pose_warmup_steps=2)
    model = create_model(config.method, config.model_config(), 0)
    graphdef, state = create_train_state(model, make_optimizer(config, 3))
    step = make_train_step(config.loss_config(), config.warmup_steps(3))
    batch = next(iter(TrainLoader([cache_root / "00"], 4, workers=0).epoch(0)))
    pose = lambda s: np.asarray(s[0]["fc_out"]["kernel"][...]).copy()
    depth = lambda s: np.asarray(s[0]["left_branch"]["heads"][0]["conv"]["kernel"][...]).copy()
    before_pose, before_depth = pose(state), depth(state)
    for k in range(3):
        state, _ = step(graphdef, state, batch, jax.random.key(k))
        if k < 2:  # warm-up: the loss saw ξ_corr = 0; the pose head stays at its zero start
            np.testing.assert_array_equal(pose(state), before_pose)
            assert not np.array_equal(depth(state), before_depth)
    assert np.abs(pose(state)).max() > 0


def test_bound_train_step_carries_the_same_state_as_a_call(cache_root: Path, cheap_losses: None) -> None:
    from dpc_jax.data.pipeline import TrainLoader

    config = tiny_config(cache_root)
    model = create_model(config.method, config.model_config(), 0)
    graphdef, state = create_train_state(model, make_optimizer(config, 3))
    step = make_train_step(config.loss_config(), 0)
    batch = next(iter(TrainLoader([cache_root / "00"], 4, workers=0).epoch(0)))
    # The step donates its state: each path starts from its own copy.
    called = jax.tree.map(jnp.copy, state)
    leaves, treedef = jax.tree.flatten(jax.tree.map(jnp.copy, state))
    bound = step.bind(graphdef, treedef)
    assert step.bind(graphdef, treedef) is bound  # compiled once per graph definition and tree
    for k in range(2):
        called, called_metrics = step(graphdef, called, batch, jax.random.key(k))
        leaves, bound_metrics = bound(leaves, batch, jax.random.key(k))
        for name, value in called_metrics.items():
            np.testing.assert_allclose(bound_metrics[name], value, rtol=1e-5, atol=1e-7)
    rebuilt = jax.tree.unflatten(treedef, leaves)
    assert jax.tree.structure(rebuilt) == jax.tree.structure(called)
    for a, b in zip(jax.tree.leaves(rebuilt), jax.tree.leaves(called), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)


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
                   "val_loss", "val_gradient_loss", "val_loop_closures", "val_delta", "val_delta_rotation",
                   "val_prior_r_err", "val_corrected_r_err"):
        assert all(r[column] != "" for r in rows), column
    assert float(rows[0]["learning_rate"]) == pytest.approx(1e-3)
    assert list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))
    ckpt = Checkpoints(tmp_path, read_only=True)
    assert ckpt.all_epochs() == [1, 2]
    assert ckpt.latest_epoch("best_gradient_loss") in (1, 2)
    assert ckpt.latest_epoch("best_loop_closures") in (1, 2)
    delta_epochs = [int(r["epoch"]) for r in rows if float(r["val_delta"]) < 0]
    best_delta = min(delta_epochs, key=lambda e: float(rows[e - 1]["val_delta"])) if delta_epochs else None
    assert ckpt.latest_epoch("best_delta") == best_delta
    stored = config_lib.load_file(tmp_path / "checkpoints" / "config.json", TrainConfig)
    assert stored == config
    split = json.loads((tmp_path / "checkpoints" / "split.json").read_text())
    assert split["train"] == ["00", "01"] and split["validation"] == ["02"] and split["steps_per_epoch"] == 3
    # The prior statistics of the training pairs (forward and skip) are stored with the run and the model.
    priors = [np.load(cache_root / n / "prior.npy") for n in ("00", "01")]
    xi = np.concatenate([se3_logs(p, 1) for p in priors] + [se3_logs(p, 2) for p in priors])
    scale = np.where(xi.std(0) > 1e-6, xi.std(0), 1.0)  # a component that never varies keeps scale 1
    np.testing.assert_allclose(split["prior_statistics"], [xi.mean(0), scale], rtol=1e-5, atol=1e-7)
    # The optimizer step count in the checkpoint is the number of updates made.
    _, fresh = create_train_state(create_model(config.method, config.model_config(), 0),
                                  make_optimizer(config, 3))
    restored, meta = ckpt.restore(jax.tree.map(ocp.utils.to_shape_dtype_struct, fresh))
    assert int(restored[1]["step"][...]) == 6 and meta["step"] == 6 and meta["data"]["next_epoch"] == 3
    np.testing.assert_allclose(np.asarray(restored[0]["prior_statistics"][...]), split["prior_statistics"],
                               rtol=1e-6)
    ckpt.close()

    with pytest.raises(ConfigError, match=r"already holds a training run.*--resume"):
        train(config, tmp_path, progress=False)
    with pytest.raises(ConfigError, match=r"different config.*epochs: 2 → 3"):
        train(tiny_config(cache_root, epochs=3), tmp_path, resume=True, progress=False)
    # Resuming a finished run with its own config does no further epoch.
    again = train(config, tmp_path, resume=True, progress=False, workers=0)
    assert again["step"] == 6 and len(_read_metrics(tmp_path)) == 2


def test_resume_from_a_damaged_checkpoint_names_it(
    cache_root: Path, tmp_path: Path, cheap_losses: None, capsys: pytest.CaptureFixture[str]
) -> None:
    from dpc_jax.cli import main
    from dpc_jax.training.checkpoints import CheckpointError

    config = tiny_config(cache_root, epochs=1, pose_warmup_epochs=0)
    train(config, tmp_path / "run", progress=False, workers=0)
    # Truncate every array file of the stored state: what a full disk or a copy cut short leaves.
    for path in (tmp_path / "run" / "checkpoints" / "epochs" / "1" / "state").rglob("*"):
        if path.is_file() and path.stat().st_size > 1000:
            path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(CheckpointError, match="cannot restore the checkpoint"):
        train(config, tmp_path / "run", resume=True, progress=False, workers=0)
    config_file = tmp_path / "tiny.py"
    config_file.write_text(f"CONFIG = {config_lib.to_dict(config)!r}\n")
    assert main(["train", "--config", str(config_file), "--workdir", str(tmp_path / "run"), "--resume",
                 "--no-progress"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and f"{tmp_path / 'run' / 'checkpoints'}: cannot restore the checkpoint" in err[0]


def test_non_finite_loss_stops_and_keeps_the_last_good_checkpoint(
    cache_root: Path, tmp_path: Path, cheap_losses: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = train_lib.make_train_step

    def poisoned(loss_config: object, warmup_steps: int = 0, mesh: object = None) -> object:
        step = real(loss_config, warmup_steps, mesh)
        calls = itertools.count()
        bind = step.bind

        def poisoned_bind(graphdef, treedef):
            bound = bind(graphdef, treedef)

            def wrapped(leaves, batch, key):  # the 5th update (epoch 2) yields NaN
                leaves, metrics = bound(leaves, batch, key)
                return leaves, {**metrics, "loss": metrics["loss"] * (jnp.nan if next(calls) == 4 else 1.0)}

            return wrapped

        step.bind = poisoned_bind
        return step

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
    split = open_data(tiny_config(cache_root), workers=0).split
    config_lib.save_json(stored / "split.json", {**split, "train_samples": 1})
    with pytest.raises(ConfigError, match=r"cannot resume: train_samples: 1 → 42$"):
        train(tiny_config(cache_root), tmp_path / "f", resume=True, progress=False)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def _subprocess_env(tmp_path: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "XLA_"))}
    env["XLA_FLAGS"] = XLA_TEST_FLAGS
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

    # The killed run's lock is reported with its pid, not taken over; once removed, the run resumes.
    refused = subprocess.run([*command, "--resume"], env=env, capture_output=True, text=True, timeout=900)
    lock = tmp_path / ".run.lock"
    assert refused.returncode == 2 and f"locked by process {process.pid}, which is no longer running" in (
        refused.stderr), refused.stderr
    lock.unlink()
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
