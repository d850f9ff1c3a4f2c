"""The choices that depend on the backend JAX runs on, in one place.

The networks (``dpc_jax.nn``) provide the mechanisms; this module picks among them for the backend
of the process (``jax.default_backend()``), so model and step code import no backend tuning:

* :func:`compiler_options`: XLA options for a jitted step. On the CPU backend,
  :data:`EIGEN_CONVOLUTIONS` for inference and for ss-DPC-Net's training step: XLA's CPU backend
  hands a convolution to its fast library (YNNPACK) only when it has more than 16 input or output
  channels, and YNNPACK computes the weight gradients of the transposed convolutions (8–64
  channels, phases at 4× the output channels) much more slowly than Eigen, while its forward
  convolutions at these channel counts are no faster; at 240×376 ss-DPC-Net's step and both
  networks' inference are faster with Eigen (measured alternating; ``benchmarks/bench_models.py``).
  Stereo DPC's training step keeps XLA's default: there the two were equal at the demo's size and
  the default slightly faster at 240×376, and the demo's trained networks stay bit for bit what
  they are. Other backends: no options.
* :func:`prepare_for_backend`: the model prepared for a sequence of inference batches, with the
  full-resolution layers on channel planes (``dpc_jax.nn.conv.conv3x3_planar``, vectorised along
  image rows for a CPU's vector units) on the CPU backend only; elsewhere the plain convolutions
  run (a GPU's convolution library does better with them). ``DPC_JAX_PLANAR=0``/``1`` overrides
  the choice.
"""

from __future__ import annotations

import os

import jax
from flax import nnx

from dpc_jax.nn import models

# YNNPACK's fusions restricted to matrix products: the convolutions fall back to Eigen.
EIGEN_CONVOLUTIONS = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"}

PLANAR_VARIABLE = "DPC_JAX_PLANAR"


def compiler_options(method: str, *, training: bool) -> dict[str, str]:
    """XLA compiler options for a jitted function that runs ``method``'s network (``jax.jit``'s
    ``compiler_options``; module docstring)."""
    if jax.default_backend() == "cpu" and (method == "ss_dpc" or not training):
        return dict(EIGEN_CONVOLUTIONS)
    return {}


def planar_inference() -> bool:
    """Whether inference runs its full-resolution layers on channel planes: on the CPU backend, unless
    ``DPC_JAX_PLANAR`` says otherwise (``0`` or ``1``)."""
    setting = os.environ.get(PLANAR_VARIABLE, "").strip()
    if setting in ("0", "1"):
        return setting == "1"
    return jax.default_backend() == "cpu"


def prepare_for_backend(graphdef: nnx.GraphDef, state: nnx.State) -> tuple[nnx.GraphDef, nnx.State]:
    """``dpc_jax.nn.models.prepare_inference`` with the path of :func:`planar_inference`."""
    return models.prepare_inference(graphdef, state, planar=planar_inference())
