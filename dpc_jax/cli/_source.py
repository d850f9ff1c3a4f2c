"""The options that say where a command's stereo frames come from, the same in every command that reads
them (``vo``, ``prepare``, ``correct``, ``live``): ``--kitti-odometry``, ``--kitti-raw`` or ``--bag`` with
what each needs, checked without JAX and opened through ``dpc_jax.sources``, so that no command branches
on the source."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from dpc_jax._io import Named
from dpc_jax.cli._common import file_path_option, input_problem, path_option

if TYPE_CHECKING:
    from dpc_jax.sources import Recording

# The options of a recording alone (with --bag), by their argparse names.
_BAG_OPTIONS = ("left_topic", "right_topic", "stamp_tolerance", "calib", "prior_topic", "gt_topic",
                "pose_frame")


def add_source_arguments(
    parser: argparse.ArgumentParser, group: argparse._MutuallyExclusiveGroup, *, many: bool = False,
    prior_topic: bool = False, layouts: bool = True,
) -> None:
    """The source options: one of ``--kitti-odometry``/``--kitti-raw``/``--bag`` in ``group`` (the
    command's choice of input), the layouts' keys (``many``: several sequences or drives) and the
    recording's topics (``prior_topic``: also ``--prior-topic``, where the command takes a prior).
    ``layouts=False``: a recording only (``live``, whose own ``--calib`` and ``--grey`` serve it)."""
    if layouts:
        group.add_argument("--kitti-odometry", type=path_option, metavar="ROOT",
                           help="odometry layout root (holds sequences/ and poses/); also the synthetic "
                           "layout")
        group.add_argument("--kitti-raw", type=path_option, metavar="ROOT",
                           help="raw layout root (holds DATE/)")
    group.add_argument("--bag", type=path_option, metavar="REC",
                       help="a ROS recording: a ROS 1 .bag, a ROS 2 bag folder (sqlite3 or MCAP storage) or "
                       "an .mcap file (docs/formats.md)")
    if layouts:
        parser.add_argument("--sequence", nargs="+" if many else None, default=[] if many else None,
                            metavar="XX", help="odometry: sequence" + ("(s)" if many else ""))
        parser.add_argument("--date", metavar="YYYY_MM_DD", help="raw: recording date, e.g. 2011_09_26")
        parser.add_argument("--drive", nargs="+" if many else None, default=[] if many else None,
                            metavar="NNNN", help="raw: drive number" + ("(s)" if many else ""))
        parser.add_argument("--grey", action="store_true",
                            help="the grey pair (odometry: image_0/image_1; raw: image_00/image_01); "
                            "default: the colour pair, or for a raw drive without one its grey pair")
    bag = parser.add_argument_group("a recording (--bag)")
    bag.add_argument("--left-topic", metavar="TOPIC",
                     help="left camera's image topic (default: the one stereo pair of image topics, whose "
                     "names differ only by left/right or 0/1)")
    bag.add_argument("--right-topic", metavar="TOPIC", help="right camera's image topic")
    bag.add_argument("--stamp-tolerance", type=float, metavar="S",
                     help="how far apart (s) a left and a right image, or a frame and its pose, may be "
                     "stamped (default: 0.01)")
    if layouts:
        bag.add_argument("--calib", type=file_path_option, metavar="FILE",
                         help="KITTI calib.txt (P2/P3, or P0/P1) for a recording without CameraInfo")
    if prior_topic:
        bag.add_argument("--prior-topic", metavar="TOPIC",
                         help="the prior: nav_msgs/Odometry, PoseStamped, PoseWithCovarianceStamped or /tf")
    bag.add_argument("--gt-topic", metavar="TOPIC", help="ground truth, of the same types as --prior-topic")
    bag.add_argument("--pose-frame", metavar="FRAME",
                     help="the frame the pose topics' poses are of (default: an odometry's or transform's "
                     "child frame; the camera's frame id if they coincide)")


def source_option(args: argparse.Namespace) -> tuple[str, Path] | None:
    """The source given: ``(kind, path)`` (``kitti-odometry``, ``kitti-raw``, ``bag``), or None."""
    for kind in ("kitti-odometry", "kitti-raw", "bag"):
        value = getattr(args, kind.replace("-", "_"), None)
        if value is not None:
            return kind, value
    return None


def source_inputs(args: argparse.Namespace) -> list[Named]:
    """The source's paths by option, for the check that no output overwrites an input."""
    return [(f"--{kind}", getattr(args, kind.replace("-", "_"), None))
            for kind in ("kitti-odometry", "kitti-raw", "bag", "calib")]


def source_problem(args: argparse.Namespace) -> str | None:
    """Why the source options do not name one source with what it needs, or None (no JAX, no reading)."""
    given = source_option(args)
    bag_only = [f"--{name.replace('_', '-')}" for name in _BAG_OPTIONS
                if getattr(args, name, None) is not None]
    if given is None:  # another input (a cache, records): its --calib is its own
        topics = [option for option in bag_only if option != "--calib"]
        return (f"{', '.join(topics)}: only used with --bag (a recording), which is not given" if topics
                else None)
    kind, path = given
    sequence, date, drive = (getattr(args, name, None) for name in ("sequence", "date", "drive"))
    if kind == "kitti-odometry":
        if not sequence or date or drive:
            return "--kitti-odometry needs --sequence (and no --date/--drive)"
    elif kind == "kitti-raw":
        if not date or not drive or sequence:
            return "--kitti-raw needs --date and --drive (and no --sequence)"
    elif sequence or date or drive or getattr(args, "grey", False):
        return ("--bag reads one recording: --sequence, --date, --drive and --grey are the KITTI layouts' "
                "options")
    if kind != "bag" and bag_only:
        return f"{', '.join(bag_only)}: only used with --bag (a recording), which is not given"
    if kind == "bag" and not path.exists():
        return f"--bag {path}: no such file or folder"
    return (input_problem(path, f"--{kind}", folder=True) if kind != "bag" else None) or input_problem(
        getattr(args, "calib", None), "--calib")


def source_keys(args: argparse.Namespace) -> list[str | None]:
    """The sequences (or drives) the options name, one ``None`` for a recording."""
    keys = getattr(args, "sequence", None) or getattr(args, "drive", None)
    if isinstance(keys, str):
        return [keys]
    return list(keys) if keys else [None]


def open_recording(args: argparse.Namespace, key: str | None = None, gt: Path | None = None) -> Recording:
    """The source's sequence ``key`` (a recording: the one), opened once per command: the options' checks
    came first (:func:`source_problem`). Its notes go to stderr, once. ``OSError``/``ValueError`` of one
    line for a source that cannot be read."""
    opened: dict[str | None, Recording] = args.__dict__.setdefault("_opened_sources", {})
    if key in opened:
        return opened[key]
    from dpc_jax.sources import DEFAULT_TOLERANCE, BagOptions, Source, open_source

    given = source_option(args)
    assert given is not None, "open_recording needs a source option"
    kind, path = given
    bag = None
    if kind == "bag":
        tolerance = args.stamp_tolerance if args.stamp_tolerance is not None else DEFAULT_TOLERANCE
        bag = BagOptions(path, args.left_topic, args.right_topic, tolerance, getattr(args, "calib", None),
                         getattr(args, "prior_topic", None), args.gt_topic, args.pose_frame)
    date = getattr(args, "date", None)
    recording = open_source(Source(kind, path, key, date, bool(getattr(args, "grey", False)), gt, bag))
    for note in recording.notes:
        print(f"dpc-jax {args.command}: note: {note}", file=sys.stderr)
    opened[key] = recording
    return recording
