"""Resumable work: one JSON record per finished unit (a stage of a run, a cell of a grid) in a folder, so
that a rerun with the same settings reuses it and an interrupted one redoes only what is missing.

A record carries the stamp of the code and machine that made it (``dpc_jax.experiments.stamp``): a rerun
may reuse records of another commit or machine, and the table says which figure came from where.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from dpc_jax._io import atomic_write


def as_json(value: Any) -> Any:
    """``value`` as it reads back from JSON (tuples become lists): what a stored key is compared with."""
    return json.loads(json.dumps(value))


class Records:
    """The records under ``folder`` (``NAME.json``), each written with ``stamp`` unless it holds its own
    (a cell measured again keeps the stamp of its training)."""

    def __init__(self, folder: Path, stamp: dict[str, str] | None = None) -> None:
        self.folder = folder
        self.stamp = stamp or {}

    def read(self, name: str) -> dict[str, Any] | None:
        """The record ``name``, or None when it was never written."""
        path = self.folder / f"{name}.json"
        return json.loads(path.read_text()) if path.is_file() else None

    def done(self, name: str, key: Any) -> dict[str, Any] | None:
        """The record ``name`` when it was made with ``key`` (its settings: a JSON-compatible value stored
        as the record's ``key``), else None: the unit is to be (re)done."""
        record = self.read(name)
        return record if record is not None and record.get("key") == as_json(key) else None

    def write(self, name: str, record: dict[str, Any]) -> dict[str, Any]:
        """Store ``record`` (atomically) with the stamp; the record as stored."""
        stored = {**record, **{k: v for k, v in self.stamp.items() if k not in record}}
        self.folder.mkdir(parents=True, exist_ok=True)
        atomic_write(self.folder / f"{name}.json", json.dumps(stored, indent=1))
        return stored

    def all(self) -> list[dict[str, Any]]:
        """Every record, by name."""
        return [json.loads(p.read_text()) for p in sorted(self.folder.glob("*.json"))]
