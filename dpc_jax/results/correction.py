"""A corrected sequence (made by ``dpc_jax.correction.corrector``; its report:
``dpc_jax.report.correction_report``)."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from typing import TypedDict

import numpy as np

from dpc_jax.eval.evaluation import Evaluation
from dpc_jax.results.acceptance import Acceptance


class AdaptationSummary(TypedDict):
    """What ``dpc_jax.correction.adapt`` did before a correction (:attr:`Correction.adaptation`)."""

    steps: int
    seconds: float
    held_out: int
    holdout_every: int
    source_epoch: int


@dataclass(frozen=True)
class Correction:
    """A corrected sequence (all trajectories ``[N, 4, 4]`` float64 camera-to-world, N cached frames).

    ``frames``: the cached frames' numbers in the source sequence; ``times`` their times (s);
    ``xi_corr [N-1, 6]``: the network's corrections; ``proposed``: the trajectory with them
    applied (only their rotation for a rotation-only run); ``corrected``: the final trajectory, with
    what ``acceptance`` applied (the prior re-composed when nothing); ``evaluation``: ``prior``,
    ``network`` (the proposal) and ``corrected`` against the ground truth, or None without ground
    truth; ``delta``: Δ ``[N-1]`` on every pair of the proposal's first component (``full``, or
    ``rotation`` for a rotation-only correction) as its prediction measured it; ``tested``: the pairs
    the acceptance test used (None: all); ``adaptation``: what
    ``dpc_jax.correction.adapt`` did first (steps, seconds, held-out pairs), if anything;
    ``choice``: how ``dpc_jax.correction.corrector.choose`` picked it among candidates (``final``,
    ``reason`` and, when two corrections were compared, the ``comparison``'s test).

    Written as :meth:`to_dict` (a report's ``summary.json``); its trajectories are written as pose files.
    """

    name: str
    frames: np.ndarray
    times: np.ndarray
    prior: np.ndarray
    proposed: np.ndarray
    corrected: np.ndarray
    ground_truth: np.ndarray | None
    xi_corr: np.ndarray
    rotation_only: bool
    acceptance: Acceptance
    epoch: int
    evaluation: Evaluation | None
    delta: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    tested: np.ndarray | None = None
    adaptation: AdaptationSummary | None = None
    choice: dict[str, object] | None = None

    @property
    def part(self) -> str:
        """What :attr:`corrected` applies, in its one name (``acceptance.part``): ``none``,
        ``rotation_xz − mean``, …"""
        return self.acceptance.part

    @property
    def all_source_frames(self) -> bool:
        """Whether the trajectory has every frame ``0 … N-1`` of its source sequence."""
        return bool(np.array_equal(self.frames, np.arange(self.frames.size)))

    def to_dict(self) -> dict[str, object]:
        """JSON-ready: the decision with every test's statistics, and the evaluation summary if any."""
        out: dict[str, object] = {
            "sequence": self.name,
            "epoch": self.epoch,
            "part": self.part,
            "rotation_only": self.rotation_only,
            "acceptance": self.acceptance.to_dict(),
        }
        if self.adaptation is not None:
            out["adaptation"] = self.adaptation
        if self.choice is not None:
            out["choice"] = self.choice
        if self.evaluation is not None:
            out["evaluation"] = json.loads(self.evaluation.to_json())
        return out
