"""``dpc-jax prepare``: build the preprocessing cache of KITTI (or synthetic) sequences."""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from dpc_jax._io import foreign_folder_problem, output_problem, overlap_problem
from dpc_jax.cli._common import (
    MAX_PIXELS,
    Formatter,
    finite_problem,
    frame_range,
    frames_problem,
    image_size,
    import_jax,
    input_problem,
    offset_problem,
    path_option,
    path_text,
    size_problem,
)
from dpc_jax.cli._source import (
    add_source_arguments,
    open_recording,
    source_inputs,
    source_keys,
    source_problem,
)
from dpc_jax.data.poses_io import FORMATS
from dpc_jax.runtime.progress import progress_mode

if TYPE_CHECKING:
    import numpy as np

    from dpc_jax.data.kitti import StereoSequence
    from dpc_jax.runtime.progress import Progress

HELP = "Decode, resize and cache stereo sequences with their VO prior (and optical flow) for training."
# No huge-page restart (dpc_jax.runtime.hugepages): decoding, resizing and flow gain nothing from it.
HUGE_PAGES = False

EPILOG = """examples:
  dpc-jax prepare --kitti-odometry ROOT --sequence 00 05 --prior 'priors/stereo_{seq}.mat' --out cache --flow
  dpc-jax prepare --kitti-raw ROOT --date 2011_09_26 --drive 1 \\
      --prior libviso2/stereo_2011_09_26_drive_0001.mat --out cache --frames 0:12 --size 120x188
  dpc-jax prepare --bag recording.mcap --prior-topic /odom --out cache --size 120x188
The synthetic sequences use the odometry layout (--kitti-odometry). '{seq}' in --prior/--gt is replaced by
each sequence name. Ground truth: poses/XX.txt (odometry), else --gt, else the poses_gt of a .mat prior.
Prints each cache folder on stdout and whether it was built or reused (up to date) on stderr.
A cache is reused when its inputs are unchanged and its files still match the sizes and digests of its
manifest (a sample of each file's bytes; --verify: every byte); else it is rebuilt. A cache written by a
newer dpc_jax is never replaced. --size may not exceed the source images (nothing is upsampled); above
4 megapixels it needs --allow-large. While a cache is built, OUT/.NAME.lock holds the process id: a second
prepare of the same cache is refused (a lock left by a killed run is reported, to be removed by hand)."""



def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.formatter_class = Formatter
    source = parser.add_mutually_exclusive_group(required=True)
    add_source_arguments(parser, source, many=True, prior_topic=True)
    parser.add_argument("--prior", type=path_text, metavar="FILE",
                        help="VO estimate per frame (KITTI/TUM text or .mat); '{seq}' = sequence name; a "
                        "recording's own prior: --prior-topic")
    parser.add_argument("--prior-format", choices=FORMATS,
                        help="format of --prior (default: from the extension or the column count)")
    parser.add_argument("--gt", type=path_text, metavar="FILE",
                        help="ground-truth pose file (KITTI/TUM/.mat); '{seq}' allowed")
    parser.add_argument("--out", required=True, type=path_option, metavar="CACHE_DIR",
                        help="cache root folder")
    parser.add_argument("--size", type=image_size, default=(240, 376), metavar="HxW",
                        help="stored image size (default: 240x376)")
    parser.add_argument("--allow-large", action="store_true",
                        help=f"accept a --size above {MAX_PIXELS / 1e6:g} megapixels per image")
    parser.add_argument("--frames", type=frame_range, metavar="START:STOP",
                        help="keep only these source frames")
    parser.add_argument("--remove-static", action="store_true", help="drop static frames (ss-DPC-Net rule)")
    parser.add_argument("--flow", action="store_true", help="store Farnebäck flow of consecutive pairs")
    parser.add_argument("--flow-augment", action="store_true",
                        help="also the flow of reversed and frame-skip pairs (implies --flow)")
    parser.add_argument("--mono-rescale", action="store_true",
                        help="rescale each prior step to the ground-truth step length (monocular VO)")
    parser.add_argument("--disparity-offset", type=float, default=0.0, metavar="PX",
                        help="the rig's disparity calibration residual (px at the source size, as "
                        "`dpc-jax vo` reports it): the right images are resampled so the stored pairs are "
                        "rectified without it")
    parser.add_argument("--force", action="store_true", help="rebuild even when the cache is up to date")
    parser.add_argument("--verify", action="store_true",
                        help="reuse a cache only when every byte of its files matches the digests of its "
                        "manifest (default: their sizes and a sample of their bytes)")
    parser.add_argument("--no-progress", action="store_true",
                        help="hide the progress bars (off a terminal: the progress lines)")


def _error(message: str, status: int = 2) -> int:
    print(f"dpc-jax prepare: error: {message}", file=sys.stderr)
    return status


def _manifest_identity(folder: Path) -> tuple[int, int] | None:
    """Inode and mtime of a cache's manifest: a rebuild installs a new folder, hence a new manifest."""
    try:
        st = (folder / "manifest.json").stat()
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns


def _poses_problem(
    sequence: StereoSequence, prior: str | np.ndarray, gt: str | None, args: argparse.Namespace
) -> str | None:
    """Why the prior or the ``--gt`` file does not hold one rigid pose per frame of ``sequence``, or None.

    Read for every sequence before the first is built, so a wrong file of the second sequence does
    not fail after the first has been prepared; the cache reads them again (a few ms) when it builds.
    """
    from dpc_jax.data.kitti import read_ground_truth
    from dpc_jax.data.priors import load_prior

    n = len(sequence)
    try:
        load_prior(prior, n, args.prior_format, frames=args.frames)
        poses = None if gt is None else read_ground_truth(gt)
    except (OSError, ValueError) as error:
        return str(error)
    if poses is not None and poses.shape[0] != n:
        return f"{gt}: {poses.shape[0]} ground-truth poses for {n} frames; expected one per frame"
    return None


def run(args: argparse.Namespace) -> int:
    problem = source_problem(args)
    if problem is None and (args.prior is None) == (getattr(args, "prior_topic", None) is None):
        problem = ("give the prior as --prior FILE or, with --bag, --prior-topic TOPIC" if args.prior is None
                   else "--prior and --prior-topic: give one prior")
    if problem is not None:
        return _error(problem)
    keys = source_keys(args)
    for option, value in (("--prior", args.prior), ("--gt", args.gt)):
        if len(keys) > 1 and value is not None and "{seq}" not in value:
            return _error(f"{option} {value}: {len(keys)} sequences would share this one file; "
                          "put {seq} in the path where the sequence name goes")
    problem = (output_problem(args.out, "--out", folder=True)
               or overlap_problem(source_inputs(args), [("--out", args.out)])
               or size_problem(args.size, args.allow_large)
               or finite_problem(disparity_offset=args.disparity_offset))
    if problem is not None:
        return _error(problem)
    # Every sequence is opened (its files listed, calibration and times read: OpenCV, no JAX) and
    # its prior and ground-truth files found before the first one is prepared.
    from dpc_jax.data.sequence_cache import MANIFEST, newer_cache_problem

    sequences = []
    for key in keys:
        try:
            recording = open_recording(args, key)
        except (OSError, ValueError, KeyError) as error:
            return _error(f"{key}: {error}" if key is not None else str(error), status=1)
        sequence = recording.sequence
        label = key or sequence.name
        problem = (frames_problem(args.frames, len(sequence), sequence.name)
                   or offset_problem(args.disparity_offset, sequence.image_size[1], sequence.name))
        if problem is not None:
            return _error(problem)
        prior_file = None if args.prior is None else args.prior.replace("{seq}", sequence.name)
        gt = None if args.gt is None else args.gt.replace("{seq}", sequence.name)
        problem = input_problem(prior_file, "--prior") or input_problem(gt, "--gt")
        if problem is not None:
            return _error(f"{label}: {problem}", status=1)
        # The cache replaces OUT/NAME: a folder there must be a cache (data.cache checks no more).
        problem = overlap_problem([("--prior", prior_file), ("--gt", gt)], [("--out", args.out)]) or (
            foreign_folder_problem(args.out / sequence.name, f"--out {args.out}", marker=MANIFEST,
                                   made_by="a cache of `dpc-jax prepare`"))
        newer = newer_cache_problem(args.out / sequence.name)
        if problem is not None or newer is not None:
            return _error(problem or f"--out {args.out}: {newer}")
        (h, w), (height, width) = sequence.image_size, args.size
        if height > h or width > w:
            return _error(f"--size {height}x{width}: larger than the source images of {sequence.name} "
                          f"({h}x{w}); a cache is never upsampled: give at most {h}x{w}")
        prior = prior_file if prior_file is not None else recording.prior
        assert prior is not None, "source_problem asks for a prior"
        problem = _poses_problem(sequence, prior, gt, args)
        if problem is not None:
            return _error(f"{label}: {problem}", status=1)
        sequences.append((label, sequence, prior, gt))
    from dpc_jax._io import LockError, new_folders_removed_on_failure, output_lock

    # A failed or interrupted run leaves no --out folder that it made and left empty. Every cache it
    # writes is locked before JAX starts, so a second prepare of one of them stops at once.
    with new_folders_removed_on_failure(args.out) as remove_new_folders, contextlib.ExitStack() as locks:
        try:
            for _, sequence, _, _ in sequences:
                locks.enter_context(output_lock(args.out / sequence.name, f"--out {args.out}"))
        except LockError as error:
            locks.close()
            remove_new_folders()
            return _error(str(error))
        import_jax()
        status = _prepare_all(args, sequences, progress_mode(args.no_progress))
        if status != 0:
            locks.close()
            remove_new_folders()
        return status


def _prepare_all(args: argparse.Namespace, sequences: list, progress: Progress) -> int:
    import time

    from dpc_jax.data.cache import prepare_sequence

    for key, sequence, prior, gt in sequences:
        try:
            before = _manifest_identity(args.out / sequence.name)
            began = time.monotonic()
            path = prepare_sequence(
                sequence,
                prior,
                args.out,
                size=args.size,
                remove_static=args.remove_static,
                flow=args.flow,
                flow_augment=args.flow_augment,
                mono_rescale=args.mono_rescale,
                frames=args.frames,
                disparity_offset=args.disparity_offset,
                prior_format=args.prior_format,
                ground_truth=gt,
                force=args.force,
                verify=args.verify,
                progress=progress,
            )
        except (OSError, ValueError, KeyError) as error:
            return _error(f"{key}: {error}", status=1)
        after = _manifest_identity(path)
        if after is not None and after == before:
            print(f"{sequence.name}: up to date, reused {path}", file=sys.stderr)
        else:
            print(f"{sequence.name}: built {path} in {time.monotonic() - began:.1f} s", file=sys.stderr)
        print(path)
    return 0
