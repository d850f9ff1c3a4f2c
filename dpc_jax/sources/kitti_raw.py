"""The KITTI raw layout as a source."""

from __future__ import annotations

from dpc_jax.data.kitti import open_raw
from dpc_jax.sources.recording import Recording, Source


def open_source(source: Source) -> Recording:
    """Drive ``KEY`` of ``DATE`` under ``ROOT``, with the ground truth of ``source.gt`` when given."""
    return Recording(open_raw(source.path, str(source.date), str(source.key), poses=source.gt,
                              cameras="grey" if source.grey else "auto"))
