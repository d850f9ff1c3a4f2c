"""Where a command's stereo frames come from: one reader per source behind one call.

Each source is a module with ``open_source(Source) -> Recording``; :func:`open_source` picks it by the
source's kind, so a command never branches on the source and a new source is one module:

* ``kitti-odometry``: the KITTI odometry layout (``kitti_odometry``), which is also the synthetic
  world's (``dpc-jax synth`` writes it);
* ``kitti-raw``: the KITTI raw layout (``kitti_raw``);
* ``bag``: a ROS 1 bag, a ROS 2 bag (sqlite3 or MCAP) or a plain MCAP file (``bag``), read with
  ``rosbags``; ``bag_images`` decodes its images, ``bag_poses`` its poses, ``odometry_out`` writes a
  corrected trajectory back as ``nav_msgs/Odometry``.

The readers import nothing above ``data`` and no JAX: a source is opened, and its problems reported,
before a command starts JAX.
"""

from __future__ import annotations

import importlib

from dpc_jax.sources.recording import DEFAULT_TOLERANCE, BagOptions, Recording, Source

KINDS = {"kitti-odometry": "kitti_odometry", "kitti-raw": "kitti_raw", "bag": "bag"}

__all__ = ["DEFAULT_TOLERANCE", "KINDS", "BagOptions", "Recording", "Source", "open_source"]


def open_source(source: Source) -> Recording:
    """Open ``source`` with its kind's reader; ``OSError``/``ValueError`` of one line naming what is wrong."""
    reader = importlib.import_module(f"dpc_jax.sources.{KINDS[source.kind]}")
    opened: Recording = reader.open_source(source)
    return opened
