"""``dpc-jax live``: an external VO's poses corrected as they arrive; and the live loop that
``dpc-jax vo --correct`` shares with it.

Both commands build one :class:`~dpc_jax.correction.live.LiveCorrector` (the network restored and
compiled before the first frame), then take the frames one at a time: each frame's corrected pose is
written as one line the moment it is computed, beside one row of the per-frame CSV, and a line once
written is never changed. The format (:data:`CSV_COLUMNS`, docs/cli.md "Live correction"):

* ``--out``: KITTI pose text, one camera-to-world row of 12 numbers per frame (``%.17g``), what
  ``dpc-jax evaluate`` reads;
* the CSV (default: OUT with suffix ``.csv``): one row per frame, written with its pose: which state
  produced the pose (``start``, ``prior``, ``forced``, or the part of the correction applied), the
  tests accepted or withdrawn at that frame, and the time of each stage;
* OUT with suffix ``.json``, at the end of the frames: the summary (states, latency percentiles,
  missed deadlines).

Every line goes out in one ``write`` with Ctrl-C held back until the frame's lines are all written
(:func:`whole_lines`), so an interrupted command leaves every file with whole lines, as many frames
as were done. Live outputs are written in place, as they grow, not through a temporary file:
after an error or Ctrl-C they hold the frames corrected before it.
"""

from __future__ import annotations

import argparse
import contextlib
import enum
import functools
import json
import math
import os
import signal
import sys
import threading
import time
from array import array
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from dpc_jax._io import (
    beside_problem,
    is_stdout,
    is_stream,
    output_problem,
    overlap_problem,
    stdout_problem,
)
from dpc_jax.cli._common import (
    Formatter,
    file_path_option,
    finite_problem,
    image_size,
    import_jax,
    input_problem,
    offset_problem,
    path_option,
    path_text,
    restore_problem,
)
from dpc_jax.cli._source import add_source_arguments, open_recording, source_problem

if TYPE_CHECKING:
    from dpc_jax.correction.live import LiveCorrector, LiveFrame
    from dpc_jax.data.calibration import Calibration

HELP = "Correct an external VO's poses live, each as its stereo pair and pose arrive (records on stdin)."
# Restart with huge-page malloc (dpc_jax.runtime.hugepages): the network runs about a quarter faster.
HUGE_PAGES = True

# The per-frame CSV of both live commands. inliers, vo_status, disparity_offset_px and vo_ms are our
# VO's (empty for an external VO, and inliers and status for frame 0, which has no pair); network_ms and
# measure_ms are empty for frame 0, judge_ms where the judge did not work; missed is 1 or 0 with
# --realtime, else empty.
CSV_COLUMNS = ("frame", "time_s", "state", "events", "inliers", "vo_status", "disparity_offset_px", "read_ms",
               "vo_ms", "prepare_ms", "network_ms", "measure_ms", "judge_ms", "latency_ms", "arrival_s",
               "written_s", "missed")
# The corrector's stages in the CSV (LiveFrame.seconds), and the times per frame the summary gives.
CORRECTION_STAGES = ("prepare", "network", "measure", "judge")
SUMMARY_STAGES = ("latency", "read", "vo", "network", "measure", "judge")
# The fields of one record: LEFT RIGHT and a KITTI pose row, optionally preceded by TIME.
POSE_FIELDS = 12
# The slowest --realtime: one frame an hour. A lower rate is a typo, and its waits overflow the clock.
MIN_RATE_HZ = 1 / 3600
RECORD_SHAPE = "LEFT RIGHT and the 12 numbers of a KITTI pose row (camera-to-world), optionally TIME first"


class Replay(enum.Enum):
    """``--realtime`` without HZ (its ``const``: argparse would pass a string through ``float``): the
    frames are replayed at their own times, a recording's header stamps."""

    OWN_TIMES = "own times"


OWN_TIMES = Replay.OWN_TIMES

EPILOG = f"""Records (--records FILE, default standard input), one frame per line, as the VO makes them:
  [TIME] LEFT RIGHT r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz
LEFT, RIGHT: the rectified stereo pair's image files (PNG/JPEG at the calibration's size; paths without
spaces, relative to the current folder); then the VO's camera-to-world pose of the left camera as a
KITTI pose row; TIME (seconds, optional) is copied to the CSV. Blank lines and lines starting with #
are skipped. A stream is read as it grows: each record is corrected when its line arrives. A regular
file (or standard input redirected from one) is checked whole before the network is loaded.

Outputs: --out gets one KITTI pose row per frame, written and flushed the moment it is computed; the
CSV (default OUT with suffix .csv; none beside a stream unless --csv) one row per frame with its pose:
{",".join(CSV_COLUMNS)}
(state: start, prior (no part accepted), forced, or the part applied: rotation, rotation − mean, full,
full − mean; events: the tests accepted or withdrawn at that frame, ';'-separated; the stage times in
ms: decoding, our VO, the pair's preparation, the network, the measurement of Δ for the tests; latency:
from the frame's arrival to its pose written). OUT with suffix .json gets the summary at
the end. Ctrl-C: exit status 130, every line written so far whole.

--realtime HZ replays a recording at the camera's rate: record k is due HZ⁻¹·k s after the first, the
command waits for it, and it misses its deadline when its pose is written after record k+1 is due.
--realtime without HZ replays a ROS recording (--bag) at its own header stamps instead.

examples:
  my_vo --stream | dpc-jax live --checkpoint runs/own_data --calib KITTI/sequences/05/calib.txt \\
      --image-size 375x1242 --out live_05.txt
  dpc-jax live --checkpoint runs/excerpt --calib ROOT/2011_09_26/calib_cam_to_cam.txt \\
      --records records.txt --realtime 10 --out live.txt
  dpc-jax live --checkpoint runs/own_data --bag run.mcap --prior-topic /odom --realtime --out live.txt
A ROS recording (--bag REC) replaces the records: its stereo frames, its CameraInfo (or --calib) and the
external VO's poses from --prior-topic (docs/formats.md, "Recordings")."""


# ----------------------------------------------------------------------------------- shared options


def add_correction_arguments(parser: argparse.ArgumentParser, *, requires: str | None) -> None:
    """The options of the live correction, shared by ``live`` and ``vo --correct``. ``requires``: the
    option they need (``--correct``), or None (always in effect); their defaults are None, so that one
    given without it can be named."""
    but = "" if requires is None else f"with {requires}: "
    parser.add_argument("--select", choices=("delta", "gradient", "loop", "last"),
                        help=f"{but}the run's epoch: most negative validation Δ (default; the newest epoch "
                        "when none beats no correction), best validation gradient loss, most loop closures, "
                        "or the newest")
    parser.add_argument("--rotation-only", action=argparse.BooleanOptionalAction, default=None,
                        help=f"{but}apply only the rotation of the correction (default: the run's "
                        "rotation_only)")
    parser.add_argument("--force", action="store_true",
                        help=f"{but}apply the correction to every pair, whatever the sequential tests say")
    parser.add_argument("--alpha", type=float, metavar="P",
                        help=f"{but}level of the sequential tests on Δ (default: 0.01): the chance that a "
                        "correction that does not help is ever accepted, however long the run")
    parser.add_argument("--no-mean-test", action="store_true",
                        help=f"{but}do not test the correction's running mean apart (whole parts only)")
    judge = parser.add_mutually_exclusive_group()
    judge.add_argument("--judge-size", type=image_size, metavar="HxW",
                       help=f"{but}a part of the correction is applied only once its sequential test passes "
                       "also on the frames prepared at this size (StereoSGBM depth, no network; default for "
                       "a stereo_dpc run: 240x376, no larger than the camera's images, as `correct`); the "
                       "judge works only while a part is accepted: about 90 ms a frame at 240x376 and 20 ms "
                       "at 120x188 on two CPU cores")
    judge.add_argument("--no-judge", action="store_true",
                       help=f"{but}decide on the network's image size alone (no judge)")
    parser.add_argument("--realtime", type=float, nargs="?", const=OWN_TIMES, metavar="HZ",
                        help=f"{but}replay at the camera's rate: frame k is due k/HZ s after the first; "
                        "without HZ at the frames' own times (a recording's header stamps); report the "
                        "frames whose pose is written after the next one is due")


def correction_problem(args: argparse.Namespace, run_option: str, run: Path | None) -> str | None:
    """Why the live correction's options do not hold (``run``: the run given to ``run_option``, None:
    not given, in which case none of the options may be), or None. Standard library only."""
    given = [name for name, value in (("--select", args.select), ("--rotation-only", args.rotation_only),
                                      ("--force", args.force or None), ("--alpha", args.alpha),
                                      ("--no-mean-test", args.no_mean_test or None),
                                      ("--judge-size", args.judge_size),
                                      ("--no-judge", args.no_judge or None),
                                      ("--realtime", args.realtime)) if value is not None]
    if run is None:
        if given:
            return (f"{', '.join(given)}: only used with {run_option} RUN (the live correction), which is "
                    "not given")
        return None
    if args.alpha is not None and not 0.0 < args.alpha < 1.0:
        return f"--alpha {args.alpha}: expected a level in (0, 1), such as 0.01"
    if args.realtime not in (None, OWN_TIMES) and not (math.isfinite(args.realtime)
                                                       and args.realtime >= MIN_RATE_HZ):
        return (f"--realtime {args.realtime}: expected the camera's rate in frames per second (> 0, at least "
                f"one frame an hour: {MIN_RATE_HZ:.3g}), such as 10")
    problem = input_problem(run, run_option, folder=True)
    if problem is None and not (run / "checkpoints" / "config.json").is_file():
        problem = (f"{run_option} {run}: not a training run (expected "
                   f"{run / 'checkpoints' / 'config.json'}, written by `dpc-jax train`)")
    return problem


def run_size_problem(args: argparse.Namespace, run: Path, run_option: str, images: tuple[int, int],
                     where: str) -> str | None:
    """Why the run's network cannot take the ``images`` (``(H, W)`` px) of ``where``, or None: its
    stored config unreadable, or its input larger than the images in either dimension (a frame is
    resized to the network's size as ``prepare`` does, which never upsamples), or ``--judge-size`` not
    between the two. Sets ``args.judge_size`` to the judge used (the default of ``correct``'s rule
    when none is given; None with ``--no-judge`` or ``--force``). Read without JAX."""
    from dpc_jax import config as config_lib
    from dpc_jax.correction.judge import judge_rule, judge_size_problem
    from dpc_jax.training.train_config import TrainConfig

    try:
        config = config_lib.load_file(run / "checkpoints" / "config.json", TrainConfig)
    except (OSError, ValueError) as error:
        return f"{run_option} {run}: {error}"
    h, w = (int(v) for v in config.resolved_image_size)
    if h > images[0] or w > images[1]:
        size = f"{images[0]}x{images[1]}"
        return (f"{run_option} {run}: the network takes {h}x{w} images, larger than the {size} images of "
                f"{where}; a frame is never upsampled: use a run trained at {size} or smaller")
    if args.no_judge or args.force:
        args.judge_size = None
    elif args.judge_size is None:
        args.judge_size = judge_rule(config.method, (h, w), images)
    elif config.method != "stereo_dpc":
        return (f"--judge-size: a judge measures Δ with stereo depth; {run_option} {run} is a "
                f"{config.method} run")
    else:
        return judge_size_problem(args.judge_size, (h, w), images)
    return None


def corrector(args: argparse.Namespace, run: Path, calibration: Calibration, *,
              disparity_offset: float = 0.0) -> LiveCorrector:
    """The live corrector of the options (JAX imported; the network restored and compiled), its first
    pose the prior's first. ``CheckpointError`` for a run that cannot be restored."""
    import logging

    from dpc_jax.correction.acceptance import DEFAULT_ALPHA
    from dpc_jax.correction.live import LiveCorrector

    # Orbax logs a warning per read-only checkpoint manager; they say nothing useful here.
    logging.getLogger("absl").setLevel(logging.ERROR)
    return LiveCorrector(run, calibration, select=args.select or "delta", rotation_only=args.rotation_only,
                         alpha=DEFAULT_ALPHA if args.alpha is None else args.alpha,
                         mean_test=not args.no_mean_test, force=args.force, disparity_offset=disparity_offset,
                         judge_size=args.judge_size)


# ------------------------------------------------------------------------------------ the live loop


class RecordError(ValueError):
    """A frame that cannot be used; its message names the frame (the record's line, the sequence's frame)."""


@dataclass(frozen=True)
class Arrived:
    """A frame as its source gives it: its ``number`` (source frame, or record index), ``time_s`` (its
    time, None if unknown), ``where`` (how a message names it) and ``load`` (decodes its images:
    the work counted in the frame's ``read_ms``)."""

    number: int
    time_s: float | None
    where: str
    load: Callable[[], Any]


@dataclass(frozen=True)
class Corrected:
    """What a frame's step gives: the corrector's ``frame``; with our VO its ``vo`` columns
    ``(inliers, status, disparity offset px)`` (None for frame 0 and an external VO) and ``vo_s``."""

    frame: LiveFrame
    vo: tuple[int, str, float] | None = None
    vo_s: float | None = None


def pose_line(pose: np.ndarray) -> str:
    """One KITTI pose row of a ``[4, 4]`` pose, as ``dpc_jax.data.poses_io.write_kitti_poses`` writes it."""
    return " ".join(f"{v:.17g}" for v in np.asarray(pose, np.float64)[:3].ravel()) + "\n"


@contextlib.contextmanager
def whole_lines() -> Iterator[None]:
    """Hold Ctrl-C back while one frame's lines are written, then deliver it: every file then ends with
    the same frame's line, whole. In the main thread only (Python runs signal handlers there)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda number, frame: pending.append(number))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if pending:
        signal.raise_signal(signal.SIGINT)


class _Line:
    """One live output: a regular file (created or truncated, parent folders made) or a stream (the
    process's standard output or error through its descriptor, else opened for appending, as
    ``dpc_jax._io.stream_write`` does), written one whole line per ``os.write``."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fd: int | None = None
        self.own = True

    def open(self) -> None:
        if is_stream(self.path):
            for stream in (sys.stdout, sys.stderr):
                with contextlib.suppress(OSError, ValueError, AttributeError):
                    stream.flush()
            status = os.stat(self.path)
            for fd in (1, 2):
                with contextlib.suppress(OSError):
                    if os.path.samestat(status, os.fstat(fd)):
                        self.fd, self.own = fd, False
                        return
            self.fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_NOCTTY)
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOCTTY, 0o666)

    def write(self, text: str) -> None:
        assert self.fd is not None
        data = text.encode("utf-8")
        while data:
            try:
                data = data[os.write(self.fd, data):]
            except OSError as error:
                raise OSError(error.errno, f"{self.path}: {error.strerror}") from None

    def close(self) -> None:
        if self.fd is not None and self.own:
            os.close(self.fd)
        self.fd = None


class LiveOutputs:
    """The live outputs of one run: ``out`` (corrected poses), ``prior`` (the prior's poses, or None)
    and ``csv`` (the per-frame rows, or None), opened together with the first frame, so that a run that
    corrects none (no records, a bad first record, Ctrl-C before it) leaves every file as it was;
    ``stale``: the summaries of an earlier run beside them, removed when they are opened (this run's are
    written at the end); ``beside``: the files named after an output rather than by the user, recorded
    as the command's own when they are opened (``dpc_jax._io.record_beside``)."""

    def __init__(self, out: Path, prior: Path | None, csv: Path | None,
                 stale: tuple[Path | None, ...], beside: tuple[Path | None, ...] = ()) -> None:
        self.lines = [_Line(path) for path in (out, prior, csv) if path is not None]
        self.has_prior, self.has_csv = prior is not None, csv is not None
        self.stale = [path for path in stale if path is not None]
        self.beside = [path for path in beside if path is not None]
        self.opened = False

    def __enter__(self) -> LiveOutputs:
        return self

    def _open(self) -> None:
        from dpc_jax._io import record_beside

        self.opened = True
        try:
            for path in self.stale:
                if path.is_file():
                    path.unlink()
            for path in self.beside:
                path.parent.mkdir(parents=True, exist_ok=True)
            record_beside(self.beside)
            for line in self.lines:
                line.open()
            if self.has_csv:
                self.lines[-1].write(",".join(CSV_COLUMNS) + "\n")
        except BaseException:
            self.close()
            raise

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for line in self.lines:
            line.close()

    def write(self, pose: np.ndarray, prior: np.ndarray, row: Callable[[float], str]) -> float:
        """Write one frame: its pose, its prior and its CSV row ``row(written)``, ``written`` the clock
        (``time.perf_counter``) when the poses were out; returns ``written``."""
        with whole_lines():
            if not self.opened:
                self._open()
            self.lines[0].write(pose_line(pose))
            if self.has_prior:
                self.lines[1].write(pose_line(prior))
            written = time.perf_counter()
            if self.has_csv:
                self.lines[-1].write(row(written))
        return written


def _ms(seconds: float | None) -> str:
    return "" if seconds is None else f"{1e3 * seconds:.3f}"


@dataclass(frozen=True)
class Pace:
    """When each frame of a replay (``--realtime``) is due, in seconds after the first frame arrived:
    frame k at ``k / hz`` (a camera's fixed rate, ``hz``), or at ``times[k] - times[0]`` (the frames' own
    times ``[N]`` s, a recording's header stamps; ``hz`` None). A frame misses its deadline when its pose
    is written after the next frame is due; the last of ``times`` has no next frame and so no deadline."""

    hz: float | None
    times: np.ndarray | None = None

    @classmethod
    def of(cls, realtime: float | Replay | None, times: np.ndarray | None) -> Pace | None:
        """The pace of ``--realtime`` (None: not given; :data:`OWN_TIMES`: the frames' ``times``)."""
        if realtime is None:
            return None
        return cls(None, np.asarray(times, np.float64)) if realtime == OWN_TIMES else cls(float(realtime))

    def due(self, k: int) -> float:
        """Frame ``k``'s due time (s after the first frame's)."""
        if self.hz is not None:
            return k / self.hz
        assert self.times is not None, "a pace of own times holds them"
        return float(self.times[k] - self.times[0]) if k < len(self.times) else math.inf

    def words(self) -> str:
        return f"{self.hz:g} Hz" if self.hz is not None else "at the frames' own stamps"


@dataclass
class LiveSummary:
    """What the command reports at the end: counts per state, the tests' events, the latency and the
    stage times per frame (one float each per frame), the frames that missed their deadline
    (``pace``: the replay's, None without ``--realtime``)."""

    pace: Pace | None
    compile_s: float
    states: Counter[str] = field(default_factory=Counter)
    events: list[tuple[int, str]] = field(default_factory=list)
    seconds: dict[str, array] = field(default_factory=lambda: {k: array("d") for k in SUMMARY_STAGES})
    missed: list[int] = field(default_factory=list)
    frames: int = 0

    def add(self, number: int, corrected: Corrected, read_s: float, latency_s: float, missed: bool) -> None:
        frame = corrected.frame
        self.frames += 1
        self.states[frame.state] += 1
        self.events += [(number, event) for event in frame.events]
        self.seconds["latency"].append(latency_s)
        self.seconds["read"].append(read_s)
        if corrected.vo_s is not None:
            self.seconds["vo"].append(corrected.vo_s)
        for stage in ("network", "measure"):
            if stage in frame.seconds:
                self.seconds[stage].append(frame.seconds[stage])
        if missed:
            self.missed.append(number)

    def percentiles(self, name: str) -> dict[str, float] | None:
        """``{"p50", "p99", "max"}`` in ms of a stage (``latency``, ``read``, ``vo``, ``network``,
        ``measure``), None when no frame had it."""
        values = np.frombuffer(self.seconds[name], np.float64) if len(self.seconds[name]) else None
        if values is None:
            return None
        p50, p99 = np.percentile(values, [50, 99])
        return {"p50": 1e3 * float(p50), "p99": 1e3 * float(p99), "max": 1e3 * float(values.max())}

    def record(self) -> dict[str, Any]:
        """The summary as the ``.json`` beside the output holds it."""
        return {
            "frames": self.frames, "compile_s": self.compile_s, "states": dict(self.states),
            "events": [{"frame": number, "event": event} for number, event in self.events],
            "ms": {name: self.percentiles(name) for name in self.seconds},
            "realtime_hz": None if self.pace is None else self.pace.hz,
            "realtime_stamps": self.pace is not None and self.pace.hz is None,
            "missed_deadlines": self.missed if self.pace is not None else None,
        }

    def lines(self) -> list[str]:
        """The lines printed at the end."""
        states = ", ".join(f"{state} {count}" for state, count in self.states.most_common())
        events = "; ".join(f"{event} at frame {number}" for number, event in self.events[:6])
        more = f" (and {len(self.events) - 6} more)" if len(self.events) > 6 else ""
        lines = [f"states: {states}; tests: {events + more if events else 'no test accepted or withdrew'}"]
        latency = self.percentiles("latency")
        if latency is not None:
            stages = [f"{name} p50 {p['p50']:.1f}" for name in ("read", "vo", "network", "measure")
                      if (p := self.percentiles(name)) is not None]
            lines.append(f"latency per frame (arrival to pose written): p50 {latency['p50']:.1f} ms, p99 "
                         f"{latency['p99']:.1f} ms, max {latency['max']:.1f} ms ({', '.join(stages)} ms); "
                         f"network restored and compiled in {self.compile_s:.1f} s before the first frame")
        if self.pace is not None:
            if self.missed:
                shown = ", ".join(map(str, self.missed[:10])) + (", ..." if len(self.missed) > 10 else "")
                lines.append(f"realtime {self.pace.words()}: {len(self.missed)} of {self.frames} frames "
                             f"missed their deadline (frames {shown})")
            else:
                lines.append(f"realtime {self.pace.words()}: every one of the {self.frames} frames met its "
                             "deadline")
        return lines


def correct_frames(
    frames: Iterator[Arrived], step: Callable[[Any], Corrected], outputs: LiveOutputs, summary: LiveSummary,
) -> None:
    """Correct each frame as it arrives and write it (module docstring).

    ``frames``: the source, which blocks until the next frame is there (a stream) or gives it at once
    (a recording); ``step``: the frame's loaded images → its correction. With ``summary.pace`` frame k
    is due ``pace.due(k)`` s after the first arrived (the command sleeps until then) and misses its
    deadline when its pose is written after frame k+1 is due; else it arrives when the source gives it. A
    frame that cannot be loaded or corrected (``ValueError``, ``OSError``) raises :class:`RecordError`
    with the frame's name (``where``) in front.
    """
    started: float | None = None
    for k, arrived in enumerate(frames):
        now = time.perf_counter()
        started = now if started is None else started
        arrival = now
        pace = summary.pace
        if pace is not None:
            arrival = started + pace.due(k)
            if now < arrival:
                time.sleep(arrival - now)
        try:
            began = time.perf_counter()
            loaded = arrived.load()
            read_s = time.perf_counter() - began
            corrected = step(loaded)
        except RecordError:
            raise
        except (OSError, ValueError) as error:
            raise RecordError(f"{arrived.where}: {error}") from None
        due = started + pace.due(k + 1) if pace is not None else math.inf
        row = functools.partial(_row, arrived, corrected, read_s, arrival - started, started, due,
                                pace is not None)
        with whole_lines():  # written and counted together: a Ctrl-C reports the frames in the files
            written = outputs.write(corrected.frame.pose, corrected.frame.prior, row)
            summary.add(arrived.number, corrected, read_s, written - arrival, written > due)


def _row(arrived: Arrived, corrected: Corrected, read_s: float, arrival_s: float, started: float, due: float,
         paced: bool, written: float) -> str:
    """The CSV row (:data:`CSV_COLUMNS`) of a frame that arrived ``arrival_s`` s after the first,
    its poses written at the clock's ``written`` (the first frame arrived at ``started``), due ``due``
    (``paced``: under ``--realtime``, which gives the ``missed`` column)."""
    frame = corrected.frame
    inliers, status, offset = corrected.vo if corrected.vo is not None else ("", "", None)
    cells = [arrived.number, "" if arrived.time_s is None else f"{arrived.time_s:.6f}", frame.state,
             ";".join(frame.events), inliers, status, "" if offset is None else f"{offset:.4f}", _ms(read_s),
             _ms(corrected.vo_s), *(_ms(frame.seconds.get(stage)) for stage in CORRECTION_STAGES),
             _ms(written - started - arrival_s), f"{arrival_s:.6f}", f"{written - started:.6f}",
             "" if not paced else int(written > due)]
    return ",".join(map(str, cells)) + "\n"


def network_words(live: LiveCorrector, run: Path) -> str:
    """``RUN (stereo_dpc, epoch 3, 64x96, judged at 240x376)``: the network of a live corrector and its
    judge, in words."""
    h, w = live.size
    judge = "" if live.judge_size is None else ", judged at {}x{}".format(*live.judge_size)
    return f"{run} ({live.run.config.method}, epoch {live.run.epoch}, {h}x{w}{judge})"


def write_summary(path: Path | None, record: dict[str, Any]) -> None:
    """The summary ``record`` as JSON at ``path`` (None: beside a stream, not made), atomically."""
    if path is not None:
        from dpc_jax._io import atomic_write

        atomic_write(path, json.dumps(record, indent=2) + "\n")


def report_stream(*paths: Path | None) -> IO[str] | None:
    """Where the command's own lines go: standard error when an output is standard output (so what
    reads it gets the poses alone), else standard output (None: ``print``'s default)."""
    return sys.stderr if any(is_stdout(path) for path in paths if path is not None) else None


# ---------------------------------------------------------------------------------- dpc-jax live


@dataclass(frozen=True)
class Record:
    """One parsed record: ``line`` (its number in the stream, from 1), ``time_s`` (None when not given),
    the image paths and the ``[4, 4]`` pose."""

    line: int
    time_s: float | None
    left: Path
    right: Path
    pose: np.ndarray


def parse_record(text: str, line: int, source: str) -> Record | None:
    """The record on line ``line`` of ``source`` (``records`` or the file), None for a blank line or a
    comment; :class:`RecordError` naming the line and what was expected."""
    from dpc_jax.geometry.poses import validate_poses

    fields = text.split()
    if not fields or fields[0].startswith("#"):
        return None
    where = f"{source} line {line}"
    if len(fields) not in (POSE_FIELDS + 2, POSE_FIELDS + 3):
        raise RecordError(f"{where}: {len(fields)} fields; expected {RECORD_SHAPE}")
    if len(fields) == POSE_FIELDS + 2 and _is_number(fields[0]) and not _is_number(fields[2]):
        # TIME LEFT RIGHT and a pose short of a number: not LEFT RIGHT and a pose whose first value is RIGHT.
        raise RecordError(f"{where}: {len(fields)} fields, TIME LEFT RIGHT and {len(fields) - 3} numbers; "
                          f"expected {RECORD_SHAPE}")
    time_s = None
    if len(fields) == POSE_FIELDS + 3:
        try:
            time_s = float(fields[0])
        except ValueError:
            raise RecordError(f"{where}: TIME {fields[0]!r} is not a number; expected "
                              f"{RECORD_SHAPE}") from None
        if not math.isfinite(time_s):
            raise RecordError(f"{where}: TIME {fields[0]} is not finite")
        fields = fields[1:]
    try:
        numbers = np.array([float(v) for v in fields[2:]], np.float64)
    except ValueError:
        bad = next(v for v in fields[2:] if not _is_number(v))
        raise RecordError(f"{where}: pose value {bad!r} is not a number; expected {RECORD_SHAPE}") from None
    pose = np.eye(4)
    pose[:3] = numbers.reshape(3, 4)
    try:
        validate_poses(pose[None], "pose")
    except ValueError as error:
        reason = str(error).removeprefix("pose: pose 0 ").removeprefix("pose: pose 0")
        raise RecordError(f"{where}: the pose {reason}; expected a rigid camera-to-world pose (a rotation "
                          "and a translation)") from None
    return Record(line, time_s, Path(fields[0]), Path(fields[1]), pose)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _image(path: Path, size: tuple[int, int], where: str, side: str) -> np.ndarray:
    """The record's ``side`` image, decoded (RGB) and checked to be ``size`` = ``(H, W)``."""
    from dpc_jax.data.kitti import load_image

    if not path.is_file():
        raise RecordError(f"{where}: {side} image {path}: no such file")
    try:
        image = load_image(path)
    except (OSError, ValueError) as error:
        raise RecordError(f"{where}: {side} image: {error}") from None
    if image.shape[:2] != tuple(size):
        raise RecordError(f"{where}: {side} image {path} is {image.shape[0]}x{image.shape[1]}, expected "
                          f"{size[0]}x{size[1]} (the calibration's image size)")
    return image


def _source(args: argparse.Namespace) -> tuple[IO[bytes], str, bool]:
    """The records' stream, its name in messages, and whether it is a regular file (read whole first)."""
    import stat

    if args.records in (None, "-"):
        stream, name = sys.stdin.buffer, "records"
    else:
        stream, name = open(args.records, "rb"), str(args.records)
    try:
        regular = stat.S_ISREG(os.fstat(stream.fileno()).st_mode)
    except (OSError, ValueError):
        regular = False
    return stream, name, regular


def _checked_records(lines: list[bytes], name: str, size: tuple[int, int],
                     args: argparse.Namespace) -> list[Record]:
    """Every record of a recording, parsed and its files found, its times increasing; the first pair
    decoded for its size and its kind (:func:`_pair_problem`)."""
    records: list[Record] = []
    for number, raw in enumerate(lines, start=1):
        record = parse_record(raw.decode("utf-8", "replace"), number, name)
        if record is None:
            continue
        where = f"{name} line {number}"
        _check_time(record, records[-1] if records else None, name)
        for side, path in (("left", record.left), ("right", record.right)):
            if not path.is_file():
                raise RecordError(f"{where}: {side} image {path}: no such file")
            if not records:
                _image(path, size, where, side)
        if not records:
            _pair_problem(record, args, where)
        records.append(record)
    if not records:
        raise RecordError(f"{name}: no records; expected one line per frame: {RECORD_SHAPE}")
    return records


def _streamed_records(stream: IO[bytes], name: str, args: argparse.Namespace) -> Iterator[Record]:
    """The records of a stream, each as soon as its line is complete (times increasing; the first one's
    images of the calibration's pair)."""
    number, previous = 0, None
    while True:
        raw = stream.readline()
        if not raw:
            return
        number += 1
        record = parse_record(raw.decode("utf-8", "replace"), number, name)
        if record is not None:
            _check_time(record, previous, name)
            if previous is None:
                _pair_problem(record, args, f"{name} line {number}")
            previous = record
            yield record


def _check_time(record: Record, previous: Record | None, name: str) -> None:
    """A record's TIME must come after the previous record's (a duplicated or reordered line otherwise)."""
    if record.time_s is not None and previous is not None and previous.time_s is not None \
            and record.time_s <= previous.time_s:
        raise RecordError(f"{name} line {record.line}: TIME {record.time_s:g} is not after line "
                          f"{previous.line}'s {previous.time_s:g}; expected increasing times, one record "
                          "per frame")


def _pair_problem(record: Record, args: argparse.Namespace, where: str) -> None:
    """With a KITTI calibration holding both pairs (grey P_rect_00/01, colour P_rect_02/03, with other
    baselines), the first record's left image must be of the pair chosen (``--grey`` or not)."""
    import cv2

    if not getattr(args, "both_pairs", False):
        return
    image = cv2.imread(str(record.left), cv2.IMREAD_UNCHANGED)
    grey = image is not None and (image.ndim == 2 or image.shape[2] == 1)
    if grey != bool(args.grey):
        fix = ("give --grey (the calibration's grey pair)" if grey
               else "leave --grey out (the calibration's colour pair)")
        raise RecordError(f"{where}: left image {record.left} is {'grey' if grey else 'colour'}, and --calib "
                          f"{args.calib} holds both pairs, with other baselines: {fix}")


def _calibration(args: argparse.Namespace) -> Calibration:
    """The stereo calibration of ``--calib`` (``dpc_jax.data.calibration.load_calibration``: its colour
    pair, or the grey one with ``--grey``) for images of ``--image-size`` (or the file's ``S_rect_XX``);
    ``ValueError`` naming the file, :class:`_UsageError` where it gives no size and none is given."""
    from dpc_jax.data.calibration import NoImageSize, load_calibration, pair_keys
    from dpc_jax.data.kitti import read_calibration

    # A KITTI file with both pairs: the records' images say which pair they are (_pair_problem).
    entries = read_calibration(args.calib)
    args.both_pairs = all(pair_keys(entries, grey) is not None for grey in (True, False))
    try:
        return load_calibration(args.calib, grey=args.grey, image_size=args.image_size)
    except NoImageSize as missing:
        raise _UsageError(f"--calib {args.calib}: does not give the images' size ({missing.reason}); give "
                          "--image-size HxW") from None


def _recorded(args: argparse.Namespace) -> tuple[Calibration, str, np.ndarray]:
    """``--bag``: the recording's calibration (``dpc_jax.sources``: its CameraInfo, or ``--calib``), how
    messages name it and its frames' times ``[N]`` (s since the first stamp); the recording is opened
    here, before JAX starts, and its frames read later."""
    from dpc_jax.data.calibration import Calibration

    sequence = open_recording(args).sequence
    return Calibration.of(sequence), f"--bag {args.bag}", sequence.times


def _recording_arrivals(args: argparse.Namespace) -> Iterator[Arrived]:
    """The frames of ``--bag``, each with its pose of ``--prior-topic``, read in order."""
    recording = open_recording(args)
    sequence, prior = recording.sequence, recording.prior
    assert prior is not None, "_check asks for --prior-topic"
    for frame in sequence.images.stream(sequence.image_size):
        def load(frame: Any = frame) -> Loaded:
            left, right = frame.decode()
            return left, right, prior[frame.index]

        yield Arrived(frame.index, float(sequence.times[frame.index]), frame.where, load)


# One record's frame, loaded: the left and right images (uint8 RGB) and the VO's pose [4, 4].
Loaded = tuple[np.ndarray, np.ndarray, np.ndarray]


class _UsageError(Exception):
    """A command-line mistake found while reading an input: exit status 2."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.formatter_class = Formatter
    parser.add_argument("--checkpoint", required=True, type=path_option, metavar="RUN",
                        help="training run folder (dpc-jax train --workdir)")
    parser.add_argument("--calib", type=path_option, metavar="FILE",
                        help="the rig's KITTI calibration: calib.txt (P2/P3) or calib_cam_to_cam.txt "
                        "(P_rect_02/P_rect_03); with --bag only for a recording without CameraInfo")
    parser.add_argument("--grey", action="store_true",
                        help="the calibration's grey pair (P0/P1, P_rect_00/P_rect_01) instead of the colour "
                        "one")
    parser.add_argument("--image-size", type=image_size, metavar="HxW",
                        help="the size of the records' images (default: the calibration's S_rect_XX)")
    records = parser.add_mutually_exclusive_group()
    records.add_argument("--records", type=path_text, metavar="FILE",
                         help="the records (default: standard input, read as it grows)")
    add_source_arguments(parser, records, prior_topic=True, layouts=False)
    parser.add_argument("--out", required=True, type=file_path_option, metavar="POSES_TXT",
                        help="corrected poses, one KITTI row per frame as it is corrected")
    parser.add_argument("--csv", type=file_path_option, metavar="FILE",
                        help="per-frame CSV (default: OUT with suffix .csv; none beside a stream)")
    parser.add_argument("--disparity-offset", type=float, default=0.0, metavar="PX",
                        help="the rig's disparity calibration residual the right images are resampled by, as "
                        "`dpc-jax prepare --disparity-offset` (px at the images' size)")
    add_correction_arguments(parser, requires=None)


def _check(args: argparse.Namespace) -> str | None:
    """The first problem of the options, paths and outputs (no JAX), or None."""
    streamed = is_stream(args.out)
    args.csv_path = args.csv if args.csv is not None or streamed else args.out.with_suffix(".csv")
    args.json_path = None if streamed else args.out.with_suffix(".json")
    records = None if args.records in (None, "-") else Path(args.records)
    problem = (correction_problem(args, "--checkpoint", args.checkpoint) or source_problem(args)
               or ("--calib FILE is required with records (the rig's calibration)"
                   if args.calib is None and args.bag is None else None)
               or ("--prior-topic TOPIC is required with --bag (the poses of the VO to correct)"
                   if args.bag is not None and args.prior_topic is None else None)
               or ("--realtime without HZ replays a recording (--bag) at its own stamps; records have none: "
                   "give the camera's rate, --realtime HZ" if args.realtime == OWN_TIMES and args.bag is None
                   else None)
               or input_problem(args.calib, "--calib") or input_problem(records, "--records")
               or finite_problem(disparity_offset=args.disparity_offset)
               or output_problem(args.out, "--out") or output_problem(args.csv_path, "--csv")
               or output_problem(args.json_path, "--out (its .json summary)"))
    if problem is not None:
        return problem
    if records is not None and records.is_dir():
        return f"--records {records}: is a folder; expected a file of records"
    inputs = [("--checkpoint", args.checkpoint), ("--calib", args.calib), ("--records", records),
              ("--bag", args.bag)]
    return (overlap_problem(inputs, [("--out", args.out), ("--csv", args.csv_path),
                                     ("--out (its .json summary)", args.json_path)])
            or stdout_problem(inputs) or beside_problem(beside_files(args.out, args.csv, args.csv_path,
                                                                     args.json_path)))


def beside_files(out: Path, csv: Path | None, csv_path: Path | None,
                 *summaries: Path | None) -> list[tuple[str, Path | None]]:
    """The live outputs named after ``out`` rather than by the user (the CSV when ``--csv`` is not given,
    the ``.json`` summaries), as ``(label, path)`` for ``dpc_jax._io.beside_problem``."""
    named = [(f"--out {out} (its .json summary)", path) for path in summaries]
    return [*([(f"--out {out} (its CSV; --csv names another)", csv_path)] if csv is None else []), *named]


def run(args: argparse.Namespace) -> int:
    def error(message: str, status: int) -> int:
        print(f"dpc-jax live: error: {message}", file=sys.stderr)
        return status

    problem = _check(args)
    if problem is not None:
        return error(problem, 2)
    try:
        calibration, where, times = _recorded(args) if args.bag is not None else (
            _calibration(args), f"--calib {args.calib}", None)
    except _UsageError as usage:
        return error(str(usage), 2)
    except (OSError, ValueError) as content:
        return error(str(content), 1)
    size = calibration.image_size
    problem = (run_size_problem(args, args.checkpoint, "--checkpoint", size, where)
               or offset_problem(args.disparity_offset, size[1], where))
    if problem is not None:
        return error(problem, 2)
    stream, name, regular = _source(args) if args.bag is None else (None, str(args.bag), True)
    with contextlib.closing(stream) if stream not in (None, sys.stdin.buffer) else contextlib.nullcontext():
        records: Iterator[Record]
        if stream is None:  # a recording, opened and checked before JAX starts
            records = iter(())
        elif regular:  # a file of records: checked whole before JAX starts
            try:
                records = iter(_checked_records(stream.readlines(), name, size, args))
            except RecordError as content:
                return error(str(content), 1)
        else:
            records = _streamed_records(stream, name, args)
        import_jax()
        from dpc_jax.training.checkpoints import CheckpointError

        began = time.perf_counter()
        try:
            live = corrector(args, args.checkpoint, calibration, disparity_offset=args.disparity_offset)
        except CheckpointError as failed:
            return error(restore_problem(failed.folder, failed.__cause__ or failed), 1)
        summary = LiveSummary(Pace.of(args.realtime, times), time.perf_counter() - began)
        report = report_stream(args.out, args.csv_path)
        outputs = LiveOutputs(args.out, None, args.csv_path, (args.json_path,),
                              tuple(path for _, path in beside_files(args.out, args.csv, args.csv_path,
                                                                     args.json_path)))

        def arrivals() -> Iterator[Arrived]:
            if args.bag is not None:
                yield from _recording_arrivals(args)
                return
            for k, record in enumerate(records):
                where = f"{name} line {record.line}"

                def load(record: Record = record, where: str = where) -> Loaded:
                    return (_image(record.left, size, where, "left"),
                            _image(record.right, size, where, "right"), record.pose)

                yield Arrived(k, record.time_s, where, load)

        def step(loaded: Loaded) -> Corrected:
            return Corrected(live(loaded[0], loaded[1], loaded[2]))

        try:
            with outputs:
                correct_frames(arrivals(), step, outputs, summary)
        except KeyboardInterrupt:
            print(f"dpc-jax live: interrupted after {summary.frames} frames; their poses in {args.out} are "
                  "whole lines", file=sys.stderr)
            raise
        except (OSError, ValueError) as content:
            return error(f"{content} (the {summary.frames} frames before it are written)", 1)
    if summary.frames == 0:
        return error(f"{name}: no records; expected one line per frame: {RECORD_SHAPE}", 1)
    network = {"checkpoint": str(args.checkpoint), "epoch": live.run.epoch, "method": live.run.config.method,
               "image_size": list(live.size)}
    write_summary(args.json_path, {"records": name, **network, **summary.record()})
    print(f"{name}: {summary.frames} frames corrected live by {network_words(live, args.checkpoint)}",
          file=report)
    for line in summary.lines():
        print(line, file=report)
    written = [path for path in (args.out, args.csv_path, args.json_path) if path is not None]
    print(f"wrote {', '.join(map(str, written))}", file=report)
    return 0
