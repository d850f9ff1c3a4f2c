"""``dpc-jax synth``: render synthetic stereo driving sequences in the KITTI odometry layout."""

from __future__ import annotations

import argparse
import sys

from dpc_jax.cli._common import image_size

HELP = "Render synthetic stereo driving sequences (KITTI odometry layout, exact depth and poses)."



def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, help="output root (receives sequences/XX and poses/XX.txt)")
    parser.add_argument("--sequences", type=int, default=4, help="number of sequences (named 00, 01, ...)")
    parser.add_argument("--frames", type=int, default=200, help="frames per sequence (10 Hz)")
    parser.add_argument("--seed", type=int, default=0, help="seed of sequence 00; sequence i uses seed + i")
    parser.add_argument("--size", type=image_size, default=(240, 376), help="image size HEIGHTxWIDTH")
    parser.add_argument("--moving-objects", type=int, default=0, help="moving cars per sequence")
    parser.add_argument("--illumination-drift", type=float, default=0.0,
                        help="amplitude X of the slow global gain (1±X) and gamma (1±X/2) drift")
    parser.add_argument("--noise", type=float, default=0.0, help="Gaussian image noise std, 0..255 units")
    parser.add_argument("--overwrite", action="store_true", help="replace existing sequences")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from dpc_jax.synth import SynthConfig, write_sequences

    try:
        config = SynthConfig(frames=args.frames, height=args.size[0], width=args.size[1], seed=args.seed,
                             moving_objects=args.moving_objects, illumination_drift=args.illumination_drift,
                             noise=args.noise)
        paths = write_sequences(args.out, config, sequences=args.sequences, overwrite=args.overwrite,
                                progress=False if args.no_progress else None)
    except (ValueError, FileExistsError) as err:
        print(f"dpc-jax synth: error: {err}", file=sys.stderr)
        return 2
    for path in paths:
        print(path)
    return 0
