"""The synthetic demo's summary (made by ``dpc_jax.pipelines.synthetic_demo.run_demo``; its report:
``dpc_jax.report.demo_report``), written as ``OUT/summary.json``."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dpc_jax.eval.evaluation import Metrics
from dpc_jax.results.acceptance import Acceptance
from dpc_jax.results.correction import AdaptationSummary

SUMMARY = "summary.json"


@dataclass(frozen=True)
class DemoSummary:
    """What a demo did and measured on its test sequence.

    ``test``: estimate → its metrics (``prior``, ``trained``, ``adapted`` when adapted, and the final
    ``corrected``); ``decisions``: network (``trained``, ``adapted``) → what its acceptance test let
    through, in words; ``acceptance``: network → its test; ``final``: which correction ``corrected.txt``
    holds (``trained``, ``adapted`` or ``prior``) and ``choice`` why; ``change_pct``: final against the
    prior, segment errors (%); ``corrected_better``: both lower; ``selected_epoch``, ``select``,
    ``steps_per_epoch``: the network's training; ``sequences``: per sequence its prior's record
    (``fallbacks``, ``pairs``, ``offset`` in px, ``error``: the prior's error composition);
    ``lengths_m``: per sequence its length; ``seconds``: per stage; ``devices``: JAX's; ``config``:
    the demo's config as data; ``adaptation``: what the adaptation did, if it ran; ``seconds_total``;
    ``report``: the report's path.
    """

    test: dict[str, Metrics]
    decisions: dict[str, str]
    acceptance: dict[str, Acceptance]
    final: str
    choice: dict[str, object] | None
    change_pct: dict[str, float]
    corrected_better: bool
    selected_epoch: int
    select: str
    steps_per_epoch: int
    sequences: dict[str, dict[str, Any]]
    lengths_m: dict[str, float]
    seconds: dict[str, float]
    devices: list[str]
    config: dict[str, Any]
    adaptation: AdaptationSummary | None = None
    seconds_total: float = 0.0
    report: str = ""

    @property
    def final_network(self) -> str:
        """The network whose correction the final trajectory holds; when it holds the prior, the last
        network tried (the adapted one when the demo adapted)."""
        if self.final in self.acceptance:
            return self.final
        return "adapted" if "adapted" in self.acceptance else "trained"

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "test": self.test, "decisions": self.decisions,
            "acceptance": {k: a.to_dict() for k, a in self.acceptance.items()}, "final": self.final,
            "choice": self.choice, "change_pct": self.change_pct, "corrected_better": self.corrected_better,
            "selected_epoch": self.selected_epoch, "select": self.select,
            "steps_per_epoch": self.steps_per_epoch, "sequences": self.sequences, "lengths_m": self.lengths_m,
            "seconds": self.seconds, "devices": self.devices, "config": self.config,
        }
        if self.adaptation is not None:
            out["adaptation"] = self.adaptation
        return {**out, "seconds_total": self.seconds_total, "report": self.report}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> DemoSummary:
        fields = {**data, "acceptance": {k: Acceptance.from_dict(a) for k, a in data["acceptance"].items()}}
        return cls(**fields)

    @classmethod
    def read(cls, out: Path) -> DemoSummary:
        """The summary of the finished demo in folder ``out``."""
        return cls.from_dict(json.loads((out / SUMMARY).read_text()))
