"""One test sequence of an experiment's fold (made by ``dpc_jax.pipelines.protocol.correct_and_evaluate``;
its table: ``dpc_jax.report.protocol_report``), written as ``WORKDIR/results.json``."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dpc_jax._io import atomic_write
from dpc_jax.eval.evaluation import Metrics

RESULTS = "results.json"


@dataclass(frozen=True)
class Final:
    """A final trajectory: what was applied (``applied``, as :attr:`FoldResult.applied`) and its metrics."""

    applied: str
    metrics: Metrics


@dataclass(frozen=True)
class FoldResult:
    """Prior and corrected figures of one test sequence (segment errors: t in %, r in °/100 m).

    ``metrics``: ``prior`` and ``corrected`` (the final trajectory) → metrics; ``applied``: which
    network's correction the final trajectory holds with what its test let through (``trained (full)``),
    or ``prior``; ``stages``: network label → its proposal's metrics; ``decisions``: network label → what
    its acceptance test let through (or ``forced``); ``decided``: the final trajectory of the same networks
    decided again by each decision the protocol asks for (``earlier``: the mean not tested apart; else an
    option of where the mean is tested, ``dpc_jax.correction.decision.MEAN_TESTS``), by its name.
    """

    fold: str
    sequence: str
    prior_label: str
    epoch: int
    selection: str
    frames: int
    metrics: dict[str, Metrics]
    applied: str = "full"
    stages: dict[str, Metrics] = field(default_factory=dict)
    decisions: dict[str, str] = field(default_factory=dict)
    decided: dict[str, Final] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> FoldResult:
        fields = dict(data)
        # Results written before the protocols decided by several options hold the earlier decision alone.
        earlier = fields.pop("earlier", None)
        decided = fields.pop("decided", {} if earlier is None else {"earlier": earlier})
        return cls(**fields, decided={name: Final(**final) for name, final in decided.items()})


def write_fold_results(path: Path, results: Sequence[FoldResult]) -> None:
    """``results`` as a JSON list at ``path`` (atomically)."""
    atomic_write(path, json.dumps([r.to_dict() for r in results], indent=1) + "\n")


def read_fold_results(path: Path) -> list[FoldResult]:
    """The results :func:`write_fold_results` wrote to ``path``."""
    return [FoldResult.from_dict(r) for r in json.loads(path.read_text())]
