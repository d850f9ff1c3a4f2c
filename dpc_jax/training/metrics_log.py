"""The training run's metrics log: ``WORKDIR/metrics.csv`` and TensorBoard events (:class:`MetricsLog`)."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any

from dpc_jax._io import atomic_write

METRICS_CSV = "metrics.csv"


class MetricsLog:
    """``WORKDIR/metrics.csv`` (one row per epoch, rewritten atomically) and TensorBoard events.

    On resume from epoch E, rows after E are dropped and TensorBoard events after E's last
    step are purged, so a redone epoch appears once. Only process 0 writes.
    """

    def __init__(self, workdir: Path, resumed_epoch: int, resumed_step: int, enabled: bool = True):
        self.path = workdir / METRICS_CSV
        self.enabled = enabled
        self.rows: list[dict[str, Any]] = []
        self.writer = None
        if not enabled:
            return
        if resumed_epoch and self.path.is_file():
            with self.path.open(newline="") as f:
                self.rows = [r for r in csv.DictReader(f) if int(r["epoch"]) <= resumed_epoch]
        from tensorboardX import SummaryWriter

        self.writer = SummaryWriter(
            str(workdir / "tensorboard"), purge_step=resumed_step + 1 if resumed_epoch else None
        )

    def scalars(self, step: int, values: dict[str, float], prefix: str) -> None:
        if self.writer is not None:
            for name, value in values.items():
                self.writer.add_scalar(f"{prefix}/{name}", value, step)

    def epoch(self, row: dict[str, Any]) -> None:
        """Append one epoch's row to ``metrics.csv`` and its scalars to TensorBoard."""
        if not self.enabled:
            return
        self.rows.append(row)
        fields = list(dict.fromkeys(k for r in self.rows for k in r))
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=fields, lineterminator="\n")
        writer.writeheader()
        writer.writerows(self.rows)
        atomic_write(self.path, buffer.getvalue())
        numbers = {k: float(v) for k, v in row.items() if k not in ("epoch", "step")}
        numbers = {k: v for k, v in numbers.items() if math.isfinite(v)}
        self.scalars(int(row["step"]), numbers, "epoch")
        if self.writer is not None:
            self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
