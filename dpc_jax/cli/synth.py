"""``dpc-jax synth``: render synthetic stereo driving sequences in the KITTI odometry layout."""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from dpc_jax._io import output_problem
from dpc_jax.cli._common import (
    MAX_PIXELS,
    Formatter,
    finite_problem,
    image_size,
    import_jax,
    path_option,
    size_problem,
)
from dpc_jax.runtime.progress import progress_mode
from dpc_jax.synth.sequence import SynthConfig

HELP = ("Render synthetic stereo driving sequences (KITTI odometry layout, exact depth and poses; or as "
        "ROS recordings).")
# --format's recordings: (dpc_jax.sources.bag_writer's kind, the name of sequence XX's recording in OUT).
RECORDINGS = {"mcap": ("mcap", "{}.mcap"), "rosbag1": ("ros1", "{}.bag"), "rosbag2": ("rosbag2", "{}")}
GROUND_TRUTH_TOPIC = "/ground_truth"
# Restart with huge-page malloc (dpc_jax.runtime.hugepages): rendering is about a sixth faster.
HUGE_PAGES = True

EPILOG = f"""examples:
  dpc-jax synth --out data/synth --sequences 4 --frames 200 --seed 0
  dpc-jax synth --out data/hard --sequences 2 --frames 300 --size 120x188 --moving-objects 3 \\
      --illumination-drift 0.3 --noise 2
Writes OUT/sequences/XX/{{image_2,image_3,depth_2,depth_3,moving_2,moving_3}}/NNNNNN.*, calib.txt,
times.txt, synth.json and OUT/poses/XX.txt; read them with --kitti-odometry OUT in the other commands.
The same command gives byte-identical files. Images above {MAX_PIXELS / 1e6:g} megapixels need --allow-large.
--format mcap|rosbag1|rosbag2 writes sequence XX as a recording instead, OUT/XX.mcap, OUT/XX.bag or the
ROS 2 bag folder OUT/XX (MCAP storage): the PNG images as CompressedImage, CameraInfo and the ground truth
on /ground_truth, stamped with times.txt's times (docs/formats.md); read it with --bag OUT/XX.mcap."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    # The rendering's defaults are SynthConfig's.
    default = SynthConfig()
    parser.formatter_class = Formatter
    parser.add_argument("--out", required=True, type=path_option, metavar="DIR",
                        help="output root (receives sequences/XX and poses/XX.txt)")
    parser.add_argument("--sequences", type=int, default=4, metavar="N",
                        help="number of sequences (named 00, 01, ...)")
    parser.add_argument("--frames", type=int, default=default.frames, metavar="N",
                        help=f"frames per sequence ({default.fps:g} Hz)")
    parser.add_argument("--seed", type=int, default=default.seed, metavar="N",
                        help="seed of sequence 00; sequence i uses seed + i")
    parser.add_argument("--size", type=image_size, default=(default.height, default.width), metavar="HxW",
                        help=f"image size HEIGHTxWIDTH (default: {default.height}x{default.width})")
    parser.add_argument("--allow-large", action="store_true",
                        help=f"accept a --size above {MAX_PIXELS / 1e6:g} megapixels per image")
    parser.add_argument("--moving-objects", type=int, default=default.moving_objects, metavar="N",
                        help="moving cars per sequence")
    parser.add_argument("--illumination-drift", type=float, default=default.illumination_drift, metavar="X",
                        help="amplitude X of the slow global gain (1±X) and gamma (1±X/2) drift")
    parser.add_argument("--noise", type=float, default=default.noise, metavar="SIGMA",
                        help="Gaussian image noise std, 0..255 units")
    parser.add_argument("--disparity-offset", type=float, default=default.disparity_offset, metavar="PX",
                        help="stereo calibration residual: every disparity measured with the written "
                        "calib.txt is PX larger than fu·B/Z (KITTI's colour pair: about -1.2 px at 1242 px)")
    parser.add_argument("--format", choices=("kitti", *RECORDINGS), default="kitti",
                        help="kitti: the KITTI odometry layout; mcap, rosbag1, rosbag2: each sequence as a "
                        "recording (a plain MCAP file, a ROS 1 bag, a ROS 2 bag folder), without depth and "
                        "masks")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace those of the sequences 00 to N-1 that exist (without it, any of them "
                        "existing is refused; sequences numbered N and above are left alone)")
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bar (off a terminal: no progress lines)")


# The fields of SynthConfig (and write_sequences' sequences) that are options of this command, as
# their messages begin with them.
_OPTIONS = {"sequences": "--sequences", "frames": "--frames", "seed": "--seed",
            "moving_objects": "--moving-objects", "illumination_drift": "--illumination-drift",
            "noise": "--noise", "disparity_offset": "--disparity-offset", "image size": "--size"}


def _option_message(message: str) -> str:
    """A message of SynthConfig's checks ("noise must be >= 0, got -1.0") with the option's name in
    place of the field's, so that it names what the user typed."""
    field = message.split(" must ", 1)[0]
    return _OPTIONS[field] + message[len(field):] if field in _OPTIONS else message


def _error(message: str) -> int:
    print(f"dpc-jax synth: error: {message}", file=sys.stderr)
    return 2


def _replaced_problem(args: argparse.Namespace) -> str | None:
    """With ``--overwrite``: why a sequence folder the run would replace is not one ``synth`` rendered
    (no ``synth.json``; a real KITTI sequence, say), or None. The folders that exist are looked at,
    not every name ``--sequences`` allows."""
    root = args.out / "sequences"
    if not args.overwrite or not root.is_dir():
        return None
    from dpc_jax._io import foreign_folder_problem

    for entry in sorted(root.iterdir()):
        name = entry.name
        if not (name.isdigit() and name == f"{int(name):02d}" and int(name) < args.sequences):
            continue  # not one of the sequences 00, 01, ... this run writes
        problem = foreign_folder_problem(entry, f"--out {args.out}", marker="synth.json",
                                         made_by="a sequence `dpc-jax synth` rendered")
        if problem is not None:
            return problem
    return None


def _recordings(args: argparse.Namespace) -> list[Path]:
    """The recordings ``--format`` names, sequence by sequence."""
    name = RECORDINGS[args.format][1]
    return [args.out / name.format(f"{k:02d}") for k in range(max(args.sequences, 0))]


def _recording_problem(args: argparse.Namespace) -> str | None:
    """Why the recordings cannot be written (one exists: a recording is never replaced), or None."""
    if args.format == "kitti":
        return None
    if args.overwrite:
        return "--overwrite replaces sequences of the KITTI layout; a recording is never replaced"
    existing = [path for path in _recordings(args) if path.exists() or path.is_symlink()]
    if existing:
        return f"--out {args.out}: {existing[0]} exists; remove it or choose another --out"
    return None


def _write_recordings(args: argparse.Namespace, config: SynthConfig) -> list[Path]:
    """Render the sequences into a temporary layout inside ``--out`` and write each as a recording, all or
    nothing; the layout is removed."""
    import numpy as np

    from dpc_jax._io import OutputSet, remove_stale, temp_name
    from dpc_jax.data.kitti import read_calibration, read_ground_truth
    from dpc_jax.sources.bag_writer import write_stereo
    from dpc_jax.synth import write_sequences

    args.out.mkdir(parents=True, exist_ok=True)
    remove_stale(args.out, ".synth-layout-")
    staging = args.out / temp_name(".synth-layout-")
    kind = RECORDINGS[args.format][0]
    paths = _recordings(args)
    try:
        folders = write_sequences(staging, config, sequences=args.sequences,
                                  progress=progress_mode(args.no_progress))
        with OutputSet() as outputs:
            for folder, path in zip(folders, paths, strict=True):
                calib = read_calibration(folder / "calib.txt")
                P2, P3 = (np.array(calib[key][1].split(), np.float64).reshape(3, 4) for key in ("P2", "P3"))
                times = np.loadtxt(folder / "times.txt", ndmin=1)
                poses = read_ground_truth(staging / "poses" / f"{folder.name}.txt")
                staged = outputs.folder(path) / path.name if kind == "rosbag2" else outputs.file(path)
                stamps = np.round(times * 1e9).astype(np.int64)
                write_stereo(staged, kind, sorted((folder / "image_2").glob("*.png")),
                             sorted((folder / "image_3").glob("*.png")), stamps, (P2, P3), compressed=True,
                             poses={GROUND_TRUTH_TOPIC: poses})
                if kind == "rosbag2":  # the bag folder's files, staged in a folder rosbags makes itself
                    for item in staged.iterdir():
                        item.rename(staged.parent / item.name)
                    staged.rmdir()
            outputs.commit()
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return paths


def run(args: argparse.Namespace) -> int:
    problem = (output_problem(args.out, "--out", folder=True) or _replaced_problem(args)
               or _recording_problem(args)
               or size_problem(args.size, args.allow_large)
               or finite_problem(illumination_drift=args.illumination_drift, noise=args.noise,
                                 disparity_offset=args.disparity_offset))
    if problem is not None:
        return _error(problem)
    from dpc_jax.synth import write_sequences  # the renderer imports JAX when it starts
    from dpc_jax.synth.writer import check_sequences_free

    try:
        config = SynthConfig(frames=args.frames, height=args.size[0], width=args.size[1], seed=args.seed,
                             moving_objects=args.moving_objects, illumination_drift=args.illumination_drift,
                             noise=args.noise, disparity_offset=args.disparity_offset)
        if not args.overwrite and args.format == "kitti":
            check_sequences_free(args.out, args.sequences)
        import_jax()
        if args.format != "kitti":
            paths = _write_recordings(args, config)
        else:
            paths = write_sequences(args.out, config, sequences=args.sequences, overwrite=args.overwrite,
                                    progress=progress_mode(args.no_progress))
    except FileExistsError as err:
        return _error(f"{err}; pass --overwrite to replace them")
    except ValueError as err:
        return _error(_option_message(str(err)))
    for path in paths:
        print(path)
    return 0
