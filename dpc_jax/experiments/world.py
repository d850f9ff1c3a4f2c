"""A synthetic world for a study: sequences rendered from one seed with the same nuisances, in the KITTI
odometry layout, and priors made from their exact ground truth by planting a rotation error."""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


@dataclass(frozen=True)
class World:
    """Sequences of ``size`` ``(H, W)`` px whose ``k``-th seed is ``seed + k``, with the
    ``dpc_jax.synth.SynthConfig`` fields of ``nuisances`` (moving cars, illumination drift, image noise,
    a stereo calibration residual; SynthConfig's defaults for those not given)."""

    size: tuple[int, int]
    seed: int
    nuisances: dict[str, Any] = field(default_factory=dict)

    def config(self, frames: int, offset: int) -> Any:
        """The ``SynthConfig`` of a sequence of ``frames`` frames seeded ``seed + offset``."""
        from dpc_jax.synth import SynthConfig

        return SynthConfig(frames=frames, height=self.size[0], width=self.size[1], seed=self.seed + offset,
                           **self.nuisances)

    def render(self, data: Path, sequences: Mapping[str, tuple[int, int]],
               say: Callable[[str], None] = print) -> list[str]:
        """Render every sequence ``name → (frames, seed offset)`` into ``data`` that is not there yet as this
        world renders it (``dpc_jax.synth.is_rendered``: a finished one of the same configuration), saying
        each; the names rendered."""
        from dpc_jax.synth import is_rendered, write_sequence

        rendered = []
        for name, (frames, offset) in sequences.items():
            if is_rendered(data, name, self.config(frames, offset)):
                continue
            began = time.perf_counter()
            write_sequence(data, name, self.config(frames, offset), overwrite=True)
            rendered.append(name)
            say(f"rendered {name}: {frames} frames at {self.size[0]}×{self.size[1]}, "
                f"{time.perf_counter() - began:.0f} s")
        return rendered

    def command(self, data: Path, sequences: Mapping[str, tuple[int, int]]) -> list[str]:
        """The command that renders ``sequences`` into ``data`` (:meth:`render`) in a process of its own:
        what a study measures (``dpc_jax.experiments.process``)."""
        spec = {"world": dataclasses.asdict(self), "sequences": dict(sequences)}
        return [sys.executable, "-m", "dpc_jax.experiments.world", str(data), json.dumps(spec)]


def planted(data: Path, name: str, bias: np.ndarray, spread: np.ndarray, seed: int) -> np.ndarray:
    """The prior ``[N, 4, 4]`` of sequence ``name`` of ``data``: its ground truth with a per-step rotation
    error of mean ``bias`` and per-axis spread ``spread`` (``[3]``, rad, camera x, y, z) planted, the
    noise drawn from ``seed`` (``dpc_jax.synth.planted_prior``)."""
    from dpc_jax.data.kitti import read_ground_truth
    from dpc_jax.synth.planted_prior import planted_prior

    return planted_prior(read_ground_truth(data / "poses" / f"{name}.txt"), bias, spread, seed=seed)


def _render(argv: Sequence[str]) -> None:
    """:meth:`World.command`'s process: ``DATA SPEC`` (the world and its sequences as JSON)."""
    data, spec = argv
    values = json.loads(spec)
    world = World(tuple(values["world"]["size"]), values["world"]["seed"], values["world"]["nuisances"])
    world.render(Path(data), {name: (n, offset) for name, (n, offset) in values["sequences"].items()})


if __name__ == "__main__":
    _render(sys.argv[1:])
