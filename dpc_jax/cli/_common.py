"""What the subcommands share (not a subcommand itself): the help formatter, argument types, the
input- and output-path checks, the checks of a run folder, a cache folder and pose files, the import
of JAX that ends the checks, progress modes, and the one-line report of a checkpoint that cannot be
read.

Output paths follow one rule in every command (``dpc_jax._io``): missing parent folders are
created when the outputs are written, the nearest existing folder must be writable, no output may
be, contain or lie inside an input or another output, a folder the command would replace must be one
it made, and an empty path is refused (:func:`path_option`); this is checked before any work starts
(:func:`~dpc_jax._io.output_problem`, :func:`~dpc_jax._io.overlap_problem`,
:func:`~dpc_jax._io.foreign_folder_problem`).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import math
import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from dpc_jax._io import nonempty_path

if TYPE_CHECKING:
    import numpy as np

    from dpc_jax.data.kitti import StereoSequence
    from dpc_jax.training.train_config import TrainConfig

# The largest --disparity-offset, as a share of the image width (SynthConfig's bound too).
MAX_OFFSET_SHARE = 0.05
# Above this many pixels per image, --size needs --allow-large: 4 MP is 8.6 times a KITTI image
# (375×1242); a synthetic stereo frame at 4 MP takes about 60 MB (two PNGs, two float32 depths).
MAX_PIXELS = 4_000_000


class Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Keeps the examples' line breaks; shows a default only where it says something.

    No "(default: None)" or "(default: False)", no second default where the help text already
    states one, and readable placeholders for options declared without a metavar.
    """

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        # By identity: 0 and 0.0 equal False, and a default of 0 is worth stating.
        nothing = action.default is None or action.default is False or action.default == []
        if nothing or action.default is argparse.SUPPRESS or "default" in text.lower():
            return text
        return super()._get_help_string(action)

    def _get_default_metavar_for_optional(self, action: argparse.Action) -> str:
        metavars: dict[object, str] = {int: "N", float: "X", path_option: "PATH", file_path_option: "FILE"}
        return metavars.get(action.type, "VALUE")


def path_text(text: str) -> str:
    """argparse type of a path option kept as text (a ``{seq}`` template, ``-`` for stdout): the
    text, unless it is empty (:func:`~dpc_jax._io.nonempty_path`)."""
    try:
        return nonempty_path(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def path_option(text: str) -> Path:
    """argparse type of a path option: ``Path(text)``, unless ``text`` is empty (``Path("")`` would
    be the current folder)."""
    return Path(path_text(text))


def file_path_text(text: str) -> str:
    """argparse type of a file output kept as text: :func:`path_text`, unless it ends in ``/``, a
    folder's spelling (``Path`` drops the slash, so a missing ``vo/new/`` would become a file ``vo/new``)."""
    text = path_text(text)
    if text.endswith("/"):
        raise argparse.ArgumentTypeError(f"{text!r} ends in '/', the spelling of a folder; expected a file "
                                         "name")
    return text


def file_path_option(text: str) -> Path:
    """argparse type of a file output: ``Path(text)`` of :func:`file_path_text`."""
    return Path(file_path_text(text))


def image_size(text: str) -> tuple[int, int]:
    """``"240x376"`` → ``(240, 376)`` (HEIGHTxWIDTH, each at least 8 pixels)."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HEIGHTxWIDTH such as 240x376, got {text!r}") from None
    if h < 8 or w < 8:
        raise argparse.ArgumentTypeError(f"image size must be at least 8x8, got {text!r}")
    return h, w


def size_problem(size: tuple[int, int], allow_large: bool) -> str | None:
    """Why ``--size`` needs ``--allow-large`` (more than ``MAX_PIXELS`` per image), or None."""
    pixels = size[0] * size[1]
    if pixels <= MAX_PIXELS or allow_large:
        return None
    return (f"--size {size[0]}x{size[1]}: {pixels / 1e6:.1f} megapixels per image, more than "
            f"{MAX_PIXELS / 1e6:.0f}; pass --allow-large if you mean it")


def frame_range(text: str) -> tuple[int, int]:
    """``"0:100"`` → ``(0, 100)``: frames START (inclusive) to STOP (exclusive)."""
    try:
        start, stop = (int(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:STOP such as 0:100, got {text!r}") from None
    if not 0 <= start < stop:
        raise argparse.ArgumentTypeError(f"expected 0 <= START < STOP, got {text!r}")
    return start, stop


def offset_problem(offset: float, width: int, name: str) -> str | None:
    """Why ``--disparity-offset`` is too large for the ``width``-pixel-wide images of the sequence
    ``name``, or None. A rig's disparity calibration residual is a pixel or two (KITTI's colour pair:
    about 1.2 px at 1242 px); 5 % of the width, the bound ``synth`` renders, is already far beyond,
    and a larger one makes every match fail, which the VO would report as bad images."""
    if abs(offset) < MAX_OFFSET_SHARE * width:
        return None
    return (f"--disparity-offset {offset:g}: the images of {name} are {width} px wide; expected a "
            f"calibration residual of a few pixels (less than {MAX_OFFSET_SHARE * width:g} px in magnitude)")


def finite_problem(**options: float) -> str | None:
    """Why one of the options (keyword ``disparity_offset`` for ``--disparity-offset``) is not a
    finite number, or None: argparse's ``float`` takes ``nan`` and ``inf``, which no option means."""
    for name, value in options.items():
        if not math.isfinite(value):
            return f"--{name.replace('_', '-')} {value}: expected a finite number"
    return None


def frames_problem(frames: tuple[int, int] | None, n_frames: int, name: str) -> str | None:
    """Why ``--frames START:STOP`` does not select at least 2 of the ``n_frames`` frames of the
    sequence ``name``, or None (no ``--frames``: all of them)."""
    if frames is None:
        return None
    start, stop = frames
    option = f"--frames {start}:{stop}"
    if stop > n_frames:
        return (f"{option}: {name} has {n_frames} frames (0 to {n_frames - 1}); STOP must be at most "
                f"{n_frames}")
    if stop - start < 2:
        return f"{option}: selects {stop - start} frame; at least 2 are needed"
    return None


def input_problem(path: Path | str | None, option: str, *, folder: bool = False) -> str | None:
    """Why ``path`` (an option's value; None = not given) is not an existing file (a folder when
    ``folder``), or None. Only the path is looked at: what the file holds is checked when it is read.
    """
    if path is None:
        return None
    path = Path(path)
    if not path.exists():
        return f"{option} {path}: no such {'folder' if folder else 'file'}"
    if folder and not path.is_dir():
        return f"{option} {path}: is a file; expected a folder"
    if not folder and path.is_dir():
        return f"{option} {path}: is a folder; expected a file"
    return None


def import_jax(*, x64: bool = False) -> None:
    """``import jax``, with Ctrl-C held back until it is complete (see :mod:`dpc_jax.cli`).

    A subcommand calls it when its checks have passed, before it imports anything that uses JAX.
    ``x64``: compute in float64 (``jax_enable_x64``).
    """
    if threading.current_thread() is not threading.main_thread():
        jax = importlib.import_module("jax")
    else:
        pending: list[int] = []
        previous = signal.signal(signal.SIGINT, lambda number, frame: pending.append(number))
        try:
            jax = importlib.import_module("jax")
        finally:
            signal.signal(signal.SIGINT, previous)
        if pending:
            raise KeyboardInterrupt
    if x64:
        jax.config.update("jax_enable_x64", True)


def restore_problem(folder: Path, error: BaseException) -> str:
    """One line for a checkpoint under ``folder`` that cannot be restored, naming the folder.

    Orbax reads a checkpoint with many concurrent tensorstore tasks. When one fails, the others
    finish after its event loop has closed and report "Event loop is closed" and "Task exception
    was never retrieved" through ``sys.unraisablehook`` and the asyncio logger, in dozens of
    tracebacks that can arrive until the process exits. The failure is reported here in one
    line, so those reports are dropped for the rest of the process.
    """
    sys.unraisablehook = lambda _: None
    logging.getLogger("asyncio").setLevel(logging.CRITICAL)
    # Orbax wraps tensorstore's error (which names the damaged array and file) in a message that
    # ends in a dump of the tensorstore spec; the innermost cause is the informative one.
    while error.__cause__ is not None:
        error = error.__cause__
    text = str(error).strip()
    first = text.splitlines()[0] if text else ""
    if len(first) > 200:
        first = first[:200] + "…"
    reason = f"{type(error).__name__}: {first}" if first else type(error).__name__
    return (f"{folder}: cannot restore the checkpoint ({reason}); it is damaged or incomplete, "
            "or was written by another version of the model code")


def stored_config(run: Path, option: str) -> TrainConfig:
    """The training config stored in the run folder ``run`` given to ``option``, read without JAX;
    ``ValueError`` with the one line to report when ``run`` is not a training run or its config cannot
    be read."""
    from dpc_jax import config as config_lib
    from dpc_jax.training.train_config import TrainConfig

    stored = run / "checkpoints" / "config.json"
    if not stored.is_file():
        raise ValueError(f"{option} {run}: not a training run (expected {stored}, written by `dpc-jax "
                         "train`)")
    try:
        return config_lib.load_file(stored, TrainConfig)
    except (OSError, ValueError) as error:
        raise ValueError(f"{option} {run}: {error}") from None


def cache_folder_problem(path: Path, option: str) -> str | None:
    """Why the folder ``path`` given to ``option`` is not one prepared sequence cache, or None; a
    folder holding caches is told to name one of them."""
    from dpc_jax.data.sequence_cache import MANIFEST

    if not path.is_dir():
        return f"{option} {path}: not a folder (expected a cache prepared by `dpc-jax prepare`)"
    if (path / MANIFEST).is_file():
        return None
    caches = sorted(p.name for p in path.iterdir() if (p / MANIFEST).is_file())
    if caches:
        more = ", ..." if len(caches) > 5 else ""
        return (f"{option} {path}: a folder of caches ({', '.join(caches[:5])}{more}), not one; give one of "
                f"them, e.g. {option} {path / caches[0]}")
    return f"{option} {path}: not a prepared cache (no {MANIFEST}); run `dpc-jax prepare`"


def poses_problem(sequence: StereoSequence, prior: str | np.ndarray, prior_format: str | None,
                  frames: tuple[int, int] | None, gt: str | None) -> str | None:
    """Why the prior (``--prior``) or the ``--gt`` file does not hold one rigid pose per frame of
    ``sequence`` (``frames``: the range the prior covers, if given), or None: read before JAX starts, as
    preparing the sequence reads them again."""
    from dpc_jax.data.kitti import read_ground_truth
    from dpc_jax.data.priors import load_prior

    try:
        load_prior(prior, len(sequence), prior_format, frames=frames)
    except (OSError, ValueError) as error:
        return f"--prior {error}"
    try:
        poses = None if gt is None else read_ground_truth(gt)
    except (OSError, ValueError) as error:
        return f"--gt {error}"
    if poses is not None and poses.shape[0] != len(sequence):
        return (f"--gt {gt}: {poses.shape[0]} ground-truth poses for the {len(sequence)} frames of "
                f"{sequence.name}; expected one per frame")
    return None


def mean_options_problem(decision: str) -> str:
    """``--decision`` (where the mean is tested) given with ``--no-mean-test`` (no mean test): one of them."""
    return (f"--decision {decision} says where the correction's mean is tested, --no-mean-test that it is "
            "not tested: give one")
