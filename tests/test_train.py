"""Training: schedule, optimizer, train/eval steps, the loop, resume, guard and bad input."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import optax
import pytest

from dpc_jax.train import TrainConfig, learning_rate_schedule, make_optimizer


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
