"""Correct a VO trajectory with a trained DPC network (``dpc-jax correct``).

Pipeline (DESIGN §1, §7):

1. :func:`load_run` restores a trained run from ``WORKDIR/checkpoints``: its ``TrainConfig``
   and the model state of the selected epoch — ``gradient`` (best validation gradient loss),
   ``loop`` (most loop closures of the corrected validation trajectory) or ``last`` (newest
   epoch checkpoint). Only the model (parameters and BatchNorm statistics) is kept.
2. :func:`predict_corrections` runs the network in evaluation mode over every consecutive frame
   pair ``(k, k+1)`` of a prepared sequence cache, in fixed-shape batches (the last one padded,
   its padding dropped), so the jitted function compiles once: ``ξ_corr [N-1, 6]``.
3. :func:`correct_cache` applies ``T*_{k+1,k} = Exp(ξ_corr,k) · T_vo_{k+1,k}`` (only the rotation
   part with ``rotation_only``, ss-DPC-Net's setting for a stereo prior) and composes the
   corrected trajectory from the first ground-truth pose when the cache has ground truth, else
   from the first prior pose; then evaluates prior and corrected against the ground truth with
   :func:`dpc_jax.evaluation.evaluate` when it exists. Composition and evaluation run in float64.

Frames: a cache holds the frames it was prepared with (``indices``: their numbers in the source
sequence). When static frames were removed or a frame range was selected at prepare time, the
corrected trajectory has one pose per *cached* frame, and consecutive poses may be several
source frames apart; :attr:`Correction.frames` says which, and the CLI writes them beside the
trajectory.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from dpc_jax.batch import Batch
from dpc_jax.data.pipeline import SequenceCache, iterate_sequence, load_cache
from dpc_jax.evaluation import Evaluation
from dpc_jax.trajectory import atomic_write, write_kitti_poses, write_tum

SELECTIONS = {"gradient": "best_gradient_loss", "loop": "best_loop_closures", "last": "epochs"}
FORMATS = ("kitti", "tum")


@dataclass(frozen=True)
class TrainedRun:
    """A restored training run: its config, the chosen epoch and the model split for inference."""

    workdir: Path
    config: Any  # dpc_jax.train.TrainConfig
    selection: str
    epoch: int
    graphdef: Any  # nnx.GraphDef of the model
    state: Any  # nnx.State of the model (parameters, BatchNorm statistics)

    @property
    def image_size(self) -> tuple[int, int]:
        """``(H, W)`` the network expects."""
        return tuple(self.config.resolved_image_size)

    @property
    def use_flow(self) -> bool:
        """Whether the network reads optical flow (the method's default unless the model says)."""
        flow = self.config.model_config().flow
        return flow if flow is not None else self.config.method == "ss_dpc"


def load_run(workdir: str | os.PathLike, select: str = "gradient") -> TrainedRun:
    """Restore the run in ``workdir`` (written by ``dpc-jax train``) at the epoch chosen by ``select``.

    ``select``: ``gradient`` | ``loop`` | ``last`` (see the module docstring). Raises
    ``FileNotFoundError`` when ``workdir`` holds no run or no checkpoint of that kind, and
    ``ValueError`` for an unknown ``select``.
    """
    import jax
    import orbax.checkpoint as ocp
    from flax import nnx

    from dpc_jax import config as config_lib
    from dpc_jax.checkpoints import Checkpoints
    from dpc_jax.models import create_model
    from dpc_jax.train import TrainConfig, create_train_state, make_optimizer

    if select not in SELECTIONS:
        raise ValueError(f"select must be one of {', '.join(SELECTIONS)}, got {select!r}")
    workdir = Path(workdir).absolute()
    config_path = workdir / "checkpoints" / "config.json"
    if not config_path.is_file():
        raise FileNotFoundError(
            f"{workdir}: not a training run (expected {config_path}, written by `dpc-jax train`)"
        )
    config = config_lib.load_file(config_path, TrainConfig)
    which = SELECTIONS[select]
    checkpoints = Checkpoints(workdir, keep_last=None, read_only=True)
    try:
        epoch = checkpoints.latest_epoch(which)
        if epoch is None:
            raise FileNotFoundError(
                f"{checkpoints.root / which}: no checkpoint to restore (--select {select}); "
                "has the run finished an epoch?"
            )
        # The stored state holds the optimizer too; its schedule does not change the state's layout.
        model = create_model(config.method, config.model_config(), config.seed)
        graphdef, initial = create_train_state(model, make_optimizer(config, 1))
        del model
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, initial)
        state, _ = checkpoints.restore(abstract, which=which, epoch=epoch)
    finally:
        checkpoints.close()
    model, _ = nnx.merge(graphdef, state)
    model.eval()
    model_graphdef, model_state = nnx.split(model)
    return TrainedRun(workdir, config, select, int(epoch), model_graphdef, model_state)


@functools.cache
def _predict_function() -> Any:
    """The jitted ``predict(graphdef, state, batch) -> ξ_corr [B, 6]`` (evaluation mode), built once."""
    import jax
    from flax import nnx

    def predict(graphdef: Any, state: Any, batch: Batch) -> Any:
        model = nnx.merge(graphdef, state)
        model.eval()
        return model(batch).xi_corr

    return jax.jit(predict, static_argnums=0)


def _check_image_size(run: TrainedRun, cache: SequenceCache) -> None:
    if cache.image_size != run.image_size:
        (h, w), (rh, rw) = cache.image_size, run.image_size
        raise ValueError(
            f"{cache.path}: images are {h}x{w}, but the run {run.workdir} expects {rh}x{rw}; "
            f"prepare the sequence with --size {rh}x{rw}"
        )


def predict_corrections(
    run: TrainedRun, cache: SequenceCache | str | os.PathLike, batch_size: int | None = None,
    progress: bool = False,
) -> np.ndarray:
    """``ξ_corr [N-1, 6]`` (numpy, the model's dtype) of the consecutive pairs of a cached sequence.

    The prior fed to the network is ``cache.prior``. Batches have ``min(batch_size, N-1)``
    samples (default: the run's batch size), the last one padded, so one compilation serves the
    whole sequence; batch k+1 is dispatched before the result of batch k is fetched.
    """
    cache = cache if isinstance(cache, SequenceCache) else load_cache(cache)
    _check_image_size(run, cache)
    pairs = len(cache) - 1
    size = max(1, min(batch_size or run.config.batch_size, pairs))
    predict = _predict_function()
    results: list[np.ndarray] = []
    pending: tuple[Any, np.ndarray] | None = None
    with contextlib.closing(iterate_sequence(cache, size, flow=run.use_flow)) as batches, tqdm(
        total=pairs, unit="pair", desc=f"correct {cache.name}", disable=not progress, leave=False
    ) as bar:
        for batch in batches:
            xi = predict(run.graphdef, run.state, batch)
            if pending is not None:
                results.append(np.asarray(pending[0])[pending[1]])
                bar.update(int(pending[1].sum()))
            pending = (xi, np.asarray(batch.weight) > 0)
        if pending is not None:
            results.append(np.asarray(pending[0])[pending[1]])
            bar.update(int(pending[1].sum()))
    xi_corr = np.concatenate(results)
    if xi_corr.shape[0] != pairs:
        raise RuntimeError(f"{cache.path}: got {xi_corr.shape[0]} corrections for {pairs} pairs")
    return xi_corr


def prior_for_cache(
    cache: SequenceCache, source: str | os.PathLike | np.ndarray, format: str | None = None
) -> np.ndarray:
    """A replacement VO prior for the frames of ``cache`` → ``[len(cache), 4, 4]`` float64.

    ``source`` (array, or KITTI/TUM/``.mat`` file as in :func:`dpc_jax.trajectory.read_trajectory`)
    holds either one pose per cached frame, or one pose per frame of the source range the cache
    was prepared from (``manifest["n_source_frames"]``), of which the cached frames
    (``cache.indices``) are taken. It is used as is (no monocular rescaling).
    """
    from dpc_jax.lie import validate_poses
    from dpc_jax.trajectory import read_trajectory

    n = len(cache)
    n_source = int(cache.manifest.get("n_source_frames", n))
    start = int(cache.manifest.get("parameters", {}).get("frames", [0])[0])
    if isinstance(source, np.ndarray):
        label, poses = "prior array", validate_poses(source, "prior array")
    else:
        label, poses = str(source), read_trajectory(source, format)
    if poses.shape[0] == n:
        return poses
    if poses.shape[0] == n_source:
        return poses[np.asarray(cache.indices) - start]
    expected = f"{n}" if n_source == n else f"{n}, one per cached frame, or {n_source}, one per source frame"
    raise ValueError(
        f"{label}: {poses.shape[0]} prior poses for the sequence in {cache.path}; expected {expected}"
    )


@dataclass(frozen=True)
class Correction:
    """A corrected sequence (all trajectories ``[N, 4, 4]`` float64 camera-to-world, N cached frames).

    ``frames``: the cached frames' numbers in the source sequence; ``times`` their times (s);
    ``xi_corr [N-1, 6]``: the network's corrections; ``evaluation``: prior (``prior``) and
    corrected (``corrected``) against the ground truth, or None without ground truth.
    """

    name: str
    frames: np.ndarray
    times: np.ndarray
    prior: np.ndarray
    corrected: np.ndarray
    ground_truth: np.ndarray | None
    xi_corr: np.ndarray
    rotation_only: bool
    evaluation: Evaluation | None

    @property
    def all_source_frames(self) -> bool:
        """Whether the trajectory has every frame ``0 … N-1`` of its source sequence."""
        return bool(np.array_equal(self.frames, np.arange(self.frames.size)))


def correct_cache(
    run: TrainedRun,
    cache: SequenceCache | str | os.PathLike,
    prior: str | os.PathLike | np.ndarray | None = None,
    *,
    rotation_only: bool | None = None,
    prior_format: str | None = None,
    batch_size: int | None = None,
    progress: bool = False,
) -> Correction:
    """Correct the prior of a cached sequence with ``run`` and evaluate it when ground truth exists.

    ``prior``: None = the cache's own prior, else a replacement (see :func:`prior_for_cache`);
    ``rotation_only``: None = the run's ``config.rotation_only``. The corrected trajectory starts
    at the first ground-truth pose when the cache has ground truth, else at the first prior pose
    (DESIGN §1).
    """
    import jax

    from dpc_jax.evaluation import evaluate
    from dpc_jax.train import corrected_trajectory

    cache = cache if isinstance(cache, SequenceCache) else load_cache(cache)
    if prior is not None:
        cache = dataclasses.replace(cache, prior=prior_for_cache(cache, prior, prior_format))
    rotation_only = run.config.rotation_only if rotation_only is None else bool(rotation_only)
    xi_corr = predict_corrections(run, cache, batch_size, progress)
    prior_poses = np.asarray(cache.prior, np.float64)
    gt = None if cache.gt is None else np.asarray(cache.gt, np.float64)
    with jax.enable_x64(True):
        first = gt[0] if gt is not None else prior_poses[0]
        corrected = corrected_trajectory(xi_corr.astype(np.float64), prior_poses, first, rotation_only)
        evaluation = None if gt is None else evaluate(gt, {"prior": prior_poses, "corrected": corrected})
    return Correction(
        name=cache.name,
        frames=np.asarray(cache.indices, np.int64),
        times=np.asarray(cache.times, np.float64),
        prior=prior_poses,
        corrected=corrected,
        ground_truth=gt,
        xi_corr=xi_corr,
        rotation_only=rotation_only,
        evaluation=evaluation,
    )


def frames_path(path: str | os.PathLike) -> Path:
    """Where :func:`write_trajectory` lists frame numbers: ``corrected.txt`` → ``corrected.frames.txt``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.frames.txt")


def write_trajectory(path: str | os.PathLike, correction: Correction, format: str = "kitti") -> list[Path]:
    """Write the corrected trajectory atomically as KITTI pose text or TUM (timestamps = frame times).

    When the trajectory lacks source frames (static frames removed or a frame range at prepare
    time), the source frame number of every pose is written too, one per line, to
    :func:`frames_path`. Returns the written paths.
    """
    if format not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {format!r}")
    path = Path(path)
    if format == "kitti":
        write_kitti_poses(path, correction.corrected)
    else:
        write_tum(path, correction.corrected, correction.times)
    written = [path]
    if not correction.all_source_frames:
        atomic_write(frames_path(path), "".join(f"{int(i)}\n" for i in correction.frames))
        written.append(frames_path(path))
    return written


def write_correction_report(directory: str | os.PathLike, correction: Correction, title: str) -> list[Path]:
    """``report.md``, CSV tables, plots and ``metrics.json`` of ``correction.evaluation`` in ``directory``."""
    from dpc_jax.evaluation import write_report

    if correction.evaluation is None:
        raise ValueError(f"{correction.name}: no ground truth, nothing to report")
    directory = Path(directory)
    written = write_report(directory, correction.evaluation, title)
    atomic_write(directory / "metrics.json", correction.evaluation.to_json())
    return [*written, directory / "metrics.json"]
