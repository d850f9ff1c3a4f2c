"""The papers' scale on a synthetic stand-in (``experiments/studies/paper_scale.py``): sequences with the
lengths of KITTI odometry 00–10, our VO, both methods' caches, a short training and a correction, each
stage the command a user runs, measured from outside its process (``dpc_jax.experiments.process``), and
the table of what each cost."""

from __future__ import annotations

import csv
import dataclasses
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax.experiments.process import Stages, folder_bytes
from dpc_jax.experiments.records import as_json
from dpc_jax.experiments.world import World

DPC_JAX = [sys.executable, "-m", "dpc_jax"]
MB = 1e6
HEADER = ["run", "stage", "method", "count", "wall (s)", "CPU (s)", "cores busy", "others' load", "rate",
          "peak RSS (MB)", "peak anon (MB)", "disk (MB)", "disk per frame (MB)", "30 epochs × 46k pairs",
          "machine", "commit", "date"]


def lengths(kitti: dict[str, int], frames: int | None) -> dict[str, int]:
    """Each sequence's frames: KITTI's, or scaled so they add up to about ``frames`` (at least 8)."""
    if frames is None:
        return dict(kitti)
    total = sum(kitti.values())
    return {name: max(8, round(n * frames / total)) for name, n in kitti.items()}


@dataclasses.dataclass(frozen=True)
class Settings:
    """One run of the stand-in: what its stages depend on (recorded with each stage). ``frames``: per
    sequence; ``size``: ``(H, W)``; ``profile``: the training length's name and ``training`` its
    TrainConfig fields; ``scale``: the config's ``SCALE`` (world seed and nuisances, the validation and
    test sequences); ``planted_bias``, ``planted_noise``: mrad per step, camera x, y, z (None: none)."""

    frames: dict[str, int]
    size: tuple[int, int]
    profile: str
    training: dict[str, object]
    scale: dict[str, Any]
    planted_bias: tuple[float, float, float] | None
    planted_noise: tuple[float, float, float]

    def key(self, *fields: str) -> Any:
        """What a stage depends on, as stored with its record."""
        return as_json({f: getattr(self, f) for f in fields})

    @property
    def world(self) -> World:
        nuisances = {k: self.scale[k] for k in ("moving_objects", "illumination_drift", "noise")}
        return World(self.size, int(self.scale["seed"]), nuisances)


def _training_config(workdir: Path, settings: Settings, method: str, base: dict) -> dict[str, Any]:
    scale = settings.scale
    held_out = (scale["test"], scale["validation"])
    return {**base, **settings.training, "image_size": tuple(settings.size),
            "cache_root": str(workdir / "cache" / method),
            "train_sequences": tuple(s for s in settings.frames if s not in held_out),
            "validation_sequences": (scale["validation"],), "test_sequences": (scale["test"],)}


def _epochs(run: Path) -> list[dict[str, str]]:
    """The rows of a finished run's ``metrics.csv``: one per epoch."""
    with (run / "metrics.csv").open() as f:
        return list(csv.DictReader(f))


def run_stages(stages: Stages, settings: Settings, methods: Sequence[str], bases: dict) -> dict[str, dict]:
    """Every stage's record: ``render``, ``vo``, then per method ``prepare_M``, ``train_M`` (``bases``:
    method → its published TrainConfig fields) and ``correct_M``."""
    from dpc_jax._io import atomic_write

    workdir, total, test = stages.workdir, sum(settings.frames.values()), str(settings.scale["test"])
    data, key = str(workdir / "data"), settings.key("frames", "size", "scale")
    sequences = {name: (n, k) for k, (name, n) in enumerate(settings.frames.items())}
    records = {"render": stages.run("render", key, [settings.world.command(workdir / "data", sequences)],
                                    count=total, unit="frames", bytes=lambda: folder_bytes(workdir / "data"))}
    (workdir / "vo").mkdir(exist_ok=True)
    records["vo"] = stages.run("vo", key, [[*DPC_JAX, "vo", "--kitti-odometry", data, "--sequence", name,
                                            "--out", str(workdir / "vo" / f"{name}.txt"), "--no-progress"]
                                           for name in settings.frames], count=total, unit="frames")
    for method in methods:
        prepare = [*DPC_JAX, "prepare", "--kitti-odometry", data, "--sequence", *settings.frames, "--prior",
                   str(workdir / "vo" / "{seq}.txt"), "--out", str(workdir / "cache" / method), "--size",
                   f"{settings.size[0]}x{settings.size[1]}", "--no-progress",
                   *["--flow-augment"] * (method == "ss_dpc")]
        records[f"prepare_{method}"] = stages.run(
            f"prepare_{method}", key, [prepare], count=total, unit="frames",
            bytes=lambda m=method: folder_bytes(workdir / "cache" / m))
    for method in methods:
        config = _training_config(workdir, settings, method, bases[method])
        run, config_file = workdir / "runs" / method, workdir / "configs" / f"{method}.py"
        train_key = {**key, "config": as_json(config)}
        if stages.records.done(f"train_{method}", train_key) is None:
            if run.exists():
                raise RuntimeError(f"{run} holds a run of other settings; remove it to train again")
            config_file.parent.mkdir(exist_ok=True)
            atomic_write(config_file, f"CONFIG = {config!r}\n")
        batch = config["batch_size"]
        records[f"train_{method}"] = stages.run(
            f"train_{method}", train_key,
            [[*DPC_JAX, "train", "--config", str(config_file), "--workdir", str(run), "--no-progress"]],
            unit="samples", count=lambda run=run, batch=batch: int(_epochs(run)[-1]["step"]) * batch,
            samples_per_s=lambda run=run: [float(e["samples_per_s"]) for e in _epochs(run)], batch_size=batch)
        correct = [*DPC_JAX, "correct", "--checkpoint", str(run), "--select", "last", "--data",
                   str(workdir / "cache" / method / test), "--out",
                   str(workdir / "corrected" / method / f"{test}.txt"), "--report",
                   str(workdir / "reports" / method / test), "--no-progress"]
        records[f"correct_{method}"] = stages.run(
            f"correct_{method}", settings.key("frames", "size", "scale", "training"), [correct],
            count=settings.frames[test], unit="frames")
    return records


def plant(workdir: Path, settings: Settings) -> None:
    """Write ``WORKDIR/planted/XX.txt``: each sequence's ground truth with the planted rotation error."""
    from dpc_jax.data.poses_io import write_kitti_poses
    from dpc_jax.experiments.world import planted

    assert settings.planted_bias is not None
    (workdir / "planted").mkdir(exist_ok=True)
    bias, noise = np.asarray(settings.planted_bias) * 1e-3, np.asarray(settings.planted_noise) * 1e-3
    for index, name in enumerate(settings.frames):
        prior = planted(workdir / "data", name, bias, noise, index)
        write_kitti_poses(workdir / "planted" / f"{name}.txt", prior)


def rows(run: str, records: dict[str, dict], cores: int, paper: tuple[int, int]) -> list[list[str]]:
    """The Scale table's rows of ``run`` (:data:`HEADER`): per stage its cost, rate, disk and, for training,
    the papers' ``paper`` = (pairs, epochs) at the last epoch's rate."""
    from dpc_jax.report.tables import EMPTY

    out = []
    for stage, record in records.items():
        kind, _, method = stage.partition("_")
        wall, disk, load = record["wall_s"], record.get("bytes"), record.get("others_cpu_s")
        if kind == "train":
            rate = record["samples_per_s"][-1] if record["samples_per_s"] else float("nan")
            rate_text = f"{rate:.2f} samples/s (batch {record['batch_size']}, after the first step)"
            extrapolated = f"{paper[0] * paper[1] / rate / 3600:.1f} h" if rate > 0 else ""
        else:
            rate = record["count"] / wall if record["count"] else float("nan")
            rate_text, extrapolated = f"{rate:.1f} {record['unit']}/s", ""
        count = "" if record.get("count") is None else f"{record['count']} {record['unit']}"
        out.append([
            run, kind, method or EMPTY, count, f"{wall:.1f}", f"{record['cpu_s']:.1f}",
            f"{record['cpu_s'] / wall / cores:.2f}",
            "not recorded" if load is None else f"{load / wall / cores:.2f}", rate_text,
            f"{record['peak_rss_mb']:.0f}", f"{record['peak_anon_mb']:.0f}",
            "" if disk is None else f"{disk / MB:.0f}",
            "" if disk is None else f"{disk / MB / record['count']:.3f}",
            extrapolated, *(record.get(field, "not recorded") for field in ("machine", "commit", "date"))])
    return out
