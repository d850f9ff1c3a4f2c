"""Tests of dpc_jax.nn.models: shapes, parameter counts, modes, split/merge under jit, gradients."""

from __future__ import annotations

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from dpc_jax.nn.batch import Batch
from dpc_jax.nn.branch import Branch, UpConv
from dpc_jax.nn.losses import stereo_dpc_loss
from dpc_jax.nn.model_config import PRESETS, ModelConfig, StereoDPCLossConfig
from dpc_jax.nn.models import create_model, prepare_inference
from dpc_jax.pipelines.protocol import SMOKE

TINY = (24, 40)
SMALL = dataclasses.replace(PRESETS["small"], image_size=TINY)
SMOKE_NETWORK = {k: tuple(v) if isinstance(v, list) else v for k, v in SMOKE["model"].items()}
"""The protocols' two-block ``--smoke`` network, as ``ModelConfig`` fields."""


def make_batch(b: int, hw: tuple[int, int], seed: int = 0, flow: bool = True) -> Batch:
    """Random images, a small prior, KITTI-like intrinsics scaled to ``hw``."""
    r = np.random.default_rng(seed)
    h, w = hw
    k = np.array([[0.6 * w, 0, w / 2], [0, 0.6 * w, h / 2], [0, 0, 1]], np.float32)
    return Batch(
        left=r.integers(0, 256, (b, 2, h, w, 3), dtype=np.uint8),
        right=r.integers(0, 256, (b, 2, h, w, 3), dtype=np.uint8),
        xi_vo=(0.05 * r.normal(size=(b, 6))).astype(np.float32),
        intrinsics=np.tile(k, (b, 1, 1)),
        baseline=np.full(b, 0.54, np.float32),
        weight=np.ones(b, np.float32),
        flow=r.normal(size=(b, 2, h, w, 2)).astype(np.float32) if flow else None,
    )


def abstract_forward(
    method: str, config: ModelConfig, batch: Batch, key: jax.Array | None = None, train: bool = False
):
    """Output shapes of a forward pass, without creating arrays or compiling."""
    model = nnx.eval_shape(lambda: create_model(method, config, 0))
    if not train:
        model.eval()
    graphdef, state = nnx.split(model)
    return jax.eval_shape(lambda s, b: nnx.merge(graphdef, s)(b, key=key), state, batch)


def n_params(model: nnx.Module) -> int:
    return sum(x.size for x in jax.tree.leaves(nnx.state(model, nnx.Param)))


# Parameter count of the PyTorch definition (utiasSTARS/ss-dpc-net models/mono_model_joint.py),
# written layer by layer from its constructor: Conv2d k·k·cin·cout + cout, BatchNorm2d 2·cout
# (weight, bias), Linear cin·cout + cout.
def _conv(k: int, cin: int, cout: int) -> int:
    return k * k * cin * cout + cout


def _linear(cin: int, cout: int) -> int:
    return cin * cout + cout


def torch_branch_count(in_channels: int, frames: int) -> int:
    p, u, ks = [8, 16, 32, 64, 128, 256, 256], [256, 128, 64, 32, 16, 8, 8], [7, 5, 3, 3, 3, 3, 3]
    n, cin = 0, in_channels
    for k, c in zip(ks, p, strict=True):
        n += _conv(k, cin, c) + 2 * c
        cin = c
    n += sum(_conv(3, a, b) for a, b in zip([p[6], *u[:6]], u, strict=True))  # depth_upconv7..1
    n += sum(_conv(3, a, b) for a, b in itertools.pairwise(u[1:]))  # mask_upconv5..1
    iconv_in = [u[0] + p[5], u[1] + p[4], u[2] + p[3], u[3] + p[2], frames + u[4] + p[1]]
    iconv_in += [frames + u[5] + p[0], frames + u[6]]
    n += sum(_conv(3, a, b) + 2 * b for a, b in zip(iconv_in, u, strict=True))
    n += sum(_conv(3, c, frames) for c in u[3:])  # predict_disp4..1
    return n + _conv(3, u[6], frames)  # predict_mask


def torch_pose_count(n_branches: int) -> int:
    bottleneck = 256 * 2 * 3  # 240×376 → 2×3 after seven stride-2 blocks
    reductions = n_branches * (_linear(bottleneck, 256) + _linear(256, 128))
    return reductions + _linear(6, 256) + _linear(256, 128) + _linear(128 * (n_branches + 1), 6)


def test_reference_parameter_count() -> None:
    mono = nnx.eval_shape(lambda: create_model("ss_dpc", PRESETS["reference"], 0))
    stereo = nnx.eval_shape(lambda: create_model("stereo_dpc", PRESETS["reference"], 0))
    assert torch_branch_count(8, 1) + torch_pose_count(1) == 4_110_619
    assert n_params(mono) == 4_110_619
    assert n_params(stereo) == 2 * torch_branch_count(6, 2) + torch_pose_count(2)
    # BatchNorm running statistics are state, not parameters.
    assert sum(x.size for x in jax.tree.leaves(nnx.state(mono, nnx.BatchStat))) == 2 * (
        sum([8, 16, 32, 64, 128, 256, 256]) + sum([256, 128, 64, 32, 16, 8, 8])
    )


@pytest.mark.parametrize("hw", [(60, 94), (120, 188), (240, 376), (97, 131)])
@pytest.mark.parametrize("method", ["ss_dpc", "stereo_dpc"])
def test_reference_output_shapes(method: str, hw: tuple[int, int]) -> None:
    """Shapes only (abstract evaluation), so the reference preset costs no compilation."""
    config = dataclasses.replace(PRESETS["reference"], image_size=hw)
    out = abstract_forward(method, config, make_batch(3, hw))
    frames = 1 if method == "ss_dpc" else 2
    assert out.xi_corr.shape == (3, 6)
    assert out.left.inv_depth.shape == out.left.mask.shape == (3, frames, *hw)
    if method == "ss_dpc":
        assert out.right is None
    else:
        assert out.right.inv_depth.shape == out.right.mask.shape == (3, 2, *hw)
    assert out.ssim_weight is None


@pytest.mark.parametrize(
    "changes",
    [
        {"flow": False},
        {"frames": 2},
        {"fc_activation": "relu", "learn_ssim_weight": True},
        {
            "encoder_planes": (8, 16, 32, 64),
            "encoder_kernels": (7, 5, 3, 3),
            "decoder_planes": (64, 32, 16, 8),
        },
        {"depth_scales": 1, "mask_source_block": 1},
        {"image_size": (5, 3)},
    ],
)
def test_config_variants_shapes(changes: dict) -> None:
    config = dataclasses.replace(SMALL, **changes)
    hw = config.image_size
    out = abstract_forward("ss_dpc", config, make_batch(2, hw, flow=config.flow is not False))
    frames = config.frames or 1
    assert out.left.inv_depth.shape == out.left.mask.shape == (2, frames, *hw)
    assert (out.ssim_weight is not None) == config.learn_ssim_weight


@pytest.mark.parametrize(
    "changes",
    [
        {"encoder_kernels": (7, 5, 3)},
        {"encoder_kernels": (7, 4, 3, 3, 3)},
        {"depth_scales": 0},
        {"mask_source_block": 6},
        {"fc_activation": "tanh"},
        {"dropout": 1.0},
        {"frames": 3},
        {"width_multiplier": 0.0},
        {"image_size": (0, 10)},
        {"pose_scale": (0.01, 0.01, 0.01)},
        {"pose_scale": (0.0, 0.0)},
        {"pose_scale": (-0.01, 0.01)},
        {"pose_features": "images"},
        {"pose_init": "xavier"},
        {"prior_dropout": 1.0},
    ],
)
def test_config_rejects_invalid(changes: dict) -> None:
    with pytest.raises(ValueError, match="invalid ModelConfig"):
        dataclasses.replace(SMALL, **changes)


def test_input_errors() -> None:
    batch = make_batch(1, TINY)
    with pytest.raises(ValueError, match=r"batch.left must have shape \[B, 2, 24, 40, 3\]"):
        abstract_forward("ss_dpc", SMALL, make_batch(1, (32, 40)))
    with pytest.raises(ValueError, match=r"batch\.right"):
        abstract_forward("stereo_dpc", SMALL, batch._replace(right=np.zeros((1, 2, 3, 4, 3))))
    with pytest.raises(ValueError, match=r"batch\.flow is None"):
        abstract_forward("ss_dpc", SMALL, make_batch(1, TINY, flow=False))
    with pytest.raises(ValueError, match=r"batch.flow must have shape \[1, 2, 24, 40, 2\]"):
        abstract_forward("ss_dpc", SMALL, batch._replace(flow=batch.flow[:, :, :-1]))
    with pytest.raises(ValueError, match="xi_vo"):
        abstract_forward("ss_dpc", SMALL, batch._replace(xi_vo=np.zeros((1, 3))))
    with pytest.raises(ValueError, match="needs key"):
        abstract_forward("ss_dpc", SMALL, batch, train=True)
    abstract_forward("ss_dpc", dataclasses.replace(SMALL, dropout=0.0), batch, train=True)
    with pytest.raises(ValueError, match="frames=2"):
        create_model("stereo_dpc", dataclasses.replace(SMALL, frames=1), 0)
    with pytest.raises(ValueError, match="unknown method"):
        create_model("mono", SMALL, 0)


@pytest.mark.slow
def test_pose_head_options_prior_statistics_scales_and_prior_only() -> None:
    """The prior enters as (ξ_vo − μ)/σ; each output component has its scale (0 switches it off); a
    prior-only head's correction does not depend on the images."""
    from dpc_jax.nn.models import set_prior_statistics

    # The pose head reads the encoder's last block: a two-block encoder (--smoke's) runs its eager calls
    # in a fraction of the small preset's time.
    config = dataclasses.replace(SMALL, pose_init="pytorch", dropout=0.0, **SMOKE_NETWORK)
    batch = make_batch(3, TINY, flow=False)
    mean, scale = np.linspace(-0.2, 0.3, 6), np.linspace(0.05, 0.5, 6)
    model = create_model("stereo_dpc", config, 0)
    model.eval()
    set_prior_statistics(model, mean, scale)
    normalised = model(batch).xi_corr
    set_prior_statistics(model, np.zeros(6), np.ones(6))
    raw = model(batch._replace(xi_vo=((batch.xi_vo - mean) / scale).astype(np.float32))).xi_corr
    np.testing.assert_allclose(np.asarray(normalised), np.asarray(raw), rtol=1e-5, atol=1e-7)

    scales = (0.0, 0.0, 0.01, 1e-4, 1e-4, 1e-4)
    reference = create_model("stereo_dpc", config, 0)
    reference.eval()
    scaled = create_model("stereo_dpc", dataclasses.replace(config, pose_scale=scales), 0)
    scaled.eval()
    ratio = np.asarray(scaled(batch).xi_corr) / np.asarray(reference(batch).xi_corr)
    np.testing.assert_allclose(ratio, np.tile(np.array(scales) / 0.01, (3, 1)), rtol=1e-5)

    prior_only = create_model("stereo_dpc", dataclasses.replace(config, pose_features="prior"), 0)
    prior_only.eval()
    other_images = make_batch(3, TINY, seed=5, flow=False)._replace(xi_vo=batch.xi_vo)
    np.testing.assert_array_equal(np.asarray(prior_only(batch).xi_corr),
                                  np.asarray(prior_only(other_images).xi_corr))
    images_too = [np.asarray(reference(b).xi_corr) for b in (batch, other_images)]
    assert not np.array_equal(*images_too)
    assert prior_only.left_reduce is None and prior_only.fc_out.kernel.shape == (config.fc_planes[1], 6)


@pytest.fixture(scope="module")
def stereo_split() -> tuple[nnx.GraphDef, nnx.State]:
    config = dataclasses.replace(SMALL, learn_ssim_weight=True)
    return nnx.split(create_model("stereo_dpc", config, 0))


@jax.jit
def _forward_eval(graphdef: nnx.GraphDef, state: nnx.State, batch: Batch, key: jax.Array):
    model = nnx.merge(graphdef, state)
    model.eval()
    return model(batch, key=key)


@jax.jit
def _forward_train(graphdef: nnx.GraphDef, state: nnx.State, batch: Batch, key: jax.Array):
    model = nnx.merge(graphdef, state)
    model.train()
    out = model(batch, key=key)
    return out, nnx.state(model)


def test_outputs_in_range(stereo_split) -> None:
    out, _ = _forward_train(*stereo_split, make_batch(2, TINY), jax.random.key(0))
    for branch in (out.left, out.right):
        assert branch.inv_depth.shape == branch.mask.shape == (2, 2, *TINY)
        assert bool(jnp.all(branch.inv_depth >= 0.0005)) and bool(jnp.all(jnp.isfinite(branch.inv_depth)))
        assert bool(jnp.all((branch.mask > 0) & (branch.mask < 1)))
    assert out.xi_corr.dtype == jnp.float32
    np.testing.assert_allclose(float(out.ssim_weight), 0.85, rtol=1e-6)


def test_eval_deterministic_and_uses_running_averages(stereo_split) -> None:
    batch = make_batch(3, TINY)
    a = _forward_eval(*stereo_split, batch, jax.random.key(0))
    b = _forward_eval(*stereo_split, batch, jax.random.key(1))
    jax.tree.map(np.testing.assert_array_equal, a, b)
    # Running averages, not batch statistics: a sample's output does not depend on the others.
    alone = _forward_eval(*stereo_split, jax.tree.map(lambda x: x[:1], batch), jax.random.key(0))
    np.testing.assert_allclose(alone.xi_corr, a.xi_corr[:1], rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(alone.left.inv_depth, a.left.inv_depth[:1], rtol=1e-4, atol=1e-7)


@pytest.mark.parametrize("method", ["ss_dpc", "stereo_dpc"])
def test_inference_on_channel_planes_equals_the_convolutions(method: str) -> None:
    """Eval mode runs the full-resolution layers with ``conv3x3_planar``: the same dense outputs
    as the NHWC convolutions that training uses (to float32 rounding), the same ξ_corr."""
    model = create_model(method, SMALL, 0)
    rng = np.random.default_rng(5)
    for _, module in nnx.iter_modules(model):
        if isinstance(module, nnx.BatchNorm):  # running averages that matter
            n = module.num_features
            for var, value in ((module.mean, rng.normal(0, 0.2, n)), (module.var, rng.uniform(0.3, 3, n)),
                               (module.scale, rng.uniform(0.5, 2, n)), (module.bias, rng.normal(0, 0.2, n))):
                assert var is not None
                var.set_value(jnp.asarray(value, jnp.float32))
    model.eval()
    branches = [module for _, module in nnx.iter_modules(model) if isinstance(module, Branch)]
    assert all(branch.planar_fits and not branch.planar_inference for branch in branches)
    batch = make_batch(2, TINY)
    prepared = prepare_inference(*nnx.split(model), planar=True)
    assert all(m.planar_inference for _, m in nnx.iter_modules(nnx.merge(*prepared)) if isinstance(m, Branch))
    planar = _forward_eval(*prepared, batch, jax.random.key(0))
    convolutions = _forward_eval(*nnx.split(model), batch, jax.random.key(0))
    np.testing.assert_array_equal(planar.xi_corr, convolutions.xi_corr)
    for got, want in zip(jax.tree.leaves(planar.left), jax.tree.leaves(convolutions.left), strict=True):
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=2e-6, atol=1e-7)


@pytest.mark.parametrize("method", ["ss_dpc", "stereo_dpc"])
def test_prepared_inference_is_the_model_bit_for_bit(method: str) -> None:
    """prepare_inference only computes the phase kernels ahead: the same outputs bit for bit; the
    source model keeps none; the prepared one refuses to train (its kernels would go stale)."""
    graphdef, state = nnx.split(create_model(method, SMALL, 0))
    prepared = prepare_inference(graphdef, state)
    batch, key = make_batch(2, TINY), jax.random.key(0)
    jax.tree.map(np.testing.assert_array_equal, _forward_eval(*prepared, batch, key),
                 _forward_eval(graphdef, state, batch, key))
    upconvs = [[m for _, m in nnx.iter_modules(nnx.merge(*split)) if isinstance(m, UpConv)]
               for split in (prepared, (graphdef, state))]
    assert upconvs[0] and all(m.phases is not None for m in upconvs[0])
    assert all(m.phases is None for m in upconvs[1])
    with pytest.raises(ValueError, match="prepared for inference"):
        _forward_train(*prepared, batch, key)


def test_wide_networks_keep_the_convolutions_in_inference() -> None:
    """A sum of 9·C_in·C_out terms per pixel stops paying, and compiling, for wide layers."""
    wide = nnx.eval_shape(lambda: create_model("ss_dpc", dataclasses.replace(SMALL, width_multiplier=4.0), 0))
    assert not wide.branch.planar_fits and not wide.branch.planar_inference


def test_the_backend_chooses_the_planar_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """On the CPU backend inference runs on channel planes, elsewhere the plain convolutions;
    DPC_JAX_PLANAR overrides the choice."""
    from dpc_jax.engine import backend

    graphdef, state = nnx.split(create_model("ss_dpc", SMALL, 0))

    def planar() -> bool:
        return bool(nnx.merge(*backend.prepare_for_backend(graphdef, state)).branch.planar_inference)

    monkeypatch.delenv(backend.PLANAR_VARIABLE, raising=False)
    assert planar() == (jax.default_backend() == "cpu")
    monkeypatch.setattr(backend.jax, "default_backend", lambda: "gpu")
    assert not planar()
    monkeypatch.setenv(backend.PLANAR_VARIABLE, "1")
    assert planar()
    monkeypatch.setenv(backend.PLANAR_VARIABLE, "0")
    monkeypatch.setattr(backend.jax, "default_backend", lambda: "cpu")
    assert not planar()


def test_train_dropout_depends_on_key(stereo_split) -> None:
    batch = make_batch(3, TINY)
    a, _ = _forward_train(*stereo_split, batch, jax.random.key(0))
    b, _ = _forward_train(*stereo_split, batch, jax.random.key(0))
    c, _ = _forward_train(*stereo_split, batch, jax.random.key(1))
    np.testing.assert_array_equal(a.xi_corr, b.xi_corr)
    assert not np.allclose(a.xi_corr, c.xi_corr)
    # Dropout acts on the pose head only: the dense outputs do not depend on the key.
    np.testing.assert_array_equal(a.left.inv_depth, c.left.inv_depth)
    # Training mode normalises with batch statistics: a sample's output depends on the batch.
    alone, _ = _forward_train(*stereo_split, jax.tree.map(lambda x: x[:2], batch), jax.random.key(0))
    assert not np.allclose(alone.left.inv_depth, a.left.inv_depth[:2])


def test_split_merge_updates_batch_statistics(stereo_split) -> None:
    """Two identical training passes from zero means: m1 = 0.1 b, m2 = 0.9 m1 + 0.1 b = 1.9 m1.

    Parameters do not change and training mode normalises with batch statistics, so every
    BatchNorm sees the same batch statistic b both times; likewise v2 = 1.9 v1 − 0.9 from v0 = 1.
    """
    graphdef, state = stereo_split
    batch = make_batch(2, TINY)
    _, state1 = _forward_train(graphdef, state, batch, jax.random.key(0))
    _, state2 = _forward_train(graphdef, state1, batch, jax.random.key(0))
    stats = [nnx.state(nnx.merge(graphdef, s), nnx.BatchStat) for s in (state, state1, state2)]
    params = [nnx.state(nnx.merge(graphdef, s), nnx.Param) for s in (state, state2)]
    jax.tree.map(np.testing.assert_array_equal, params[0], params[1])
    paths0 = jax.tree_util.tree_leaves_with_path(stats[0])
    assert len(paths0) == 2 * 2 * (5 + 5)  # mean and var of 10 BatchNorms per branch
    for (path, s0), s1, s2 in zip(paths0, jax.tree.leaves(stats[1]), jax.tree.leaves(stats[2]), strict=True):
        name = jax.tree_util.keystr(path)
        assert not np.allclose(s0, s1), name
        if "mean" in name:
            np.testing.assert_array_equal(s0, 0.0)
            np.testing.assert_allclose(s2, 1.9 * s1, rtol=2e-5, atol=1e-7, err_msg=name)
        else:
            np.testing.assert_array_equal(s0, 1.0)
            np.testing.assert_allclose(s2, 1.9 * s1 - 0.9, rtol=2e-5, atol=1e-6, err_msg=name)


@pytest.mark.slow
def test_stereo_loss_gradient_reaches_every_parameter(stereo_split) -> None:
    model = nnx.merge(*stereo_split)
    model.train()
    gd, params, others = nnx.split(model, nnx.Param, ...)
    batch = make_batch(2, TINY, seed=3)

    @jax.jit
    def loss_fn(p: nnx.State, others: nnx.State) -> jax.Array:
        m = nnx.merge(gd, p, others)
        outputs = m(batch, key=jax.random.key(2))

        return stereo_dpc_loss(outputs, batch, StereoDPCLossConfig())[0]

    grads = jax.grad(loss_fn)(params, others)
    leaves = jax.tree_util.tree_leaves_with_path(grads)
    assert len(leaves) == len(jax.tree.leaves(params))
    for path, g in leaves:
        assert np.all(np.isfinite(g)), jax.tree_util.keystr(path)
        assert np.any(g != 0), jax.tree_util.keystr(path)


def test_jit_compiles_once_per_shape() -> None:
    model = create_model("ss_dpc", SMALL, 0)
    model.eval()
    graphdef, state = nnx.split(model)
    traces = []

    @jax.jit
    def forward(state: nnx.State, batch: Batch) -> jax.Array:
        traces.append(batch.left.shape)
        return nnx.merge(graphdef, state)(batch).xi_corr

    for seed in range(3):
        forward(state, make_batch(2, TINY, seed))
    assert traces == [(2, 2, *TINY, 3)]
    forward(state, make_batch(1, TINY))
    forward(state, make_batch(1, TINY, 5))
    assert traces == [(2, 2, *TINY, 3), (1, 2, *TINY, 3)]
    assert forward._cache_size() == 2


def test_model_config_is_hashable_static() -> None:
    """The config rides in the graphdef, which jit hashes as a static argument."""
    assert hash(PRESETS["small"]) == hash(dataclasses.replace(PRESETS["small"]))
    assert isinstance(PRESETS["reference"], ModelConfig)
