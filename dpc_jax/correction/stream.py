"""The live correction of a stream of frames: each frame's corrected pose written the moment it is
computed (``dpc-jax live`` and ``dpc-jax vo --correct``; docs/cli.md "Live correction").

:func:`correct_frames` takes the frames one at a time from their source (:class:`Arrived`: an external
VO's records, :func:`record_arrivals`; a recording with its prior, :func:`prior_arrivals`; a sequence
our VO runs on, :func:`sequence_arrivals`), corrects each with a step (a
:class:`~dpc_jax.correction.live.LiveCorrector`, or our VO before it, :class:`VOStep`: a
:class:`Corrected`) and writes it through :func:`live_outputs`, one line per output and frame, a line
once written never changed:

* the corrected poses: KITTI pose text, one camera-to-world row of 12 numbers per frame (``%.17g``,
  ``dpc_jax.data.poses_io.kitti_line``), what ``dpc-jax evaluate`` reads; beside them, optionally, the
  prior's;
* the CSV: one row per frame (:data:`CSV_COLUMNS`), written with its pose: which state produced the
  pose (``start``, ``prior``, ``forced``, or the part of the correction applied), the tests accepted or
  withdrawn at that frame, and the time of each stage.

With a :class:`Pace` (``--realtime``) the frames are replayed at the camera's rate or their own times,
and a frame whose pose is written after the next one is due misses its deadline. :class:`LiveSummary`
gathers what the commands report at the end (states, latency percentiles, missed deadlines) and the
``.json`` record of it (:func:`write_summary`). The outputs' lines are whole whatever interrupts them
(``dpc_jax._io.LiveOutputs``).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import json
import math
import time
from array import array
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dpc_jax._io import LiveOutputs, atomic_write, whole_lines
from dpc_jax.data.poses_io import kitti_line
from dpc_jax.data.records import Record, RecordError, record_image

if TYPE_CHECKING:
    from dpc_jax.correction.live import LiveCorrector, LiveFrame
    from dpc_jax.data.kitti import StereoSequence
    from dpc_jax.vo import StereoVO, VOResult

# The per-frame CSV. inliers, vo_status, disparity_offset_px and vo_ms are our VO's (empty for an
# external VO, and inliers and status for frame 0, which has no pair); network_ms and measure_ms are
# empty for frame 0, judge_ms where the judge did not work; missed is 1 or 0 under a pace, else empty;
# measured: 1 when the pair's Δ are measured for the tests, 0 when skipped (behind, under a pace), empty
# for frame 0. Measured behind the poses, measure_ms and judge_ms are those of the pair fed at the frame.
CSV_COLUMNS = ("frame", "time_s", "state", "events", "inliers", "vo_status", "disparity_offset_px", "read_ms",
               "vo_ms", "prepare_ms", "network_ms", "measure_ms", "judge_ms", "latency_ms", "arrival_s",
               "written_s", "missed", "measured")
# The corrector's stages in the CSV (LiveFrame.seconds), and the times per frame the summary gives.
CORRECTION_STAGES = ("prepare", "network", "measure", "judge")
SUMMARY_STAGES = ("latency", "read", "vo", "network", "measure", "judge")
# The slowest pace: one frame an hour. A lower rate is a typo, and its waits overflow the clock.
MIN_RATE_HZ = 1 / 3600


class Replay(enum.Enum):
    """A replay at the frames' own times, a recording's header stamps (``--realtime`` without HZ: its
    ``const``, which argparse would pass through ``float`` were it a string)."""

    OWN_TIMES = "own times"


OWN_TIMES = Replay.OWN_TIMES


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
        """The pace of a replay at ``realtime`` Hz (``--realtime``; None: none, the frames taken as they
        come; :data:`OWN_TIMES`: at the frames' ``times`` ``[N]`` s)."""
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
    skipped: list[int] = field(default_factory=list)
    frames: int = 0

    def add(self, number: int, corrected: Corrected, read_s: float, latency_s: float, missed: bool) -> None:
        frame = corrected.frame
        self.frames += 1
        self.states[frame_state(frame)] += 1
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
        if not frame.measured:
            self.skipped.append(number)

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
            "skipped_pairs": self.skipped,
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
                lines.append(f"realtime {self.pace.words()}: {len(self.missed)} of {self.frames} frames "
                             f"missed their deadline (frames {_listed(self.missed)})")
            else:
                lines.append(f"realtime {self.pace.words()}: every one of the {self.frames} frames met its "
                             "deadline")
            pairs = max(self.frames - 1, 0)
            skipped = f" (skipped: {_listed(self.skipped)})" if self.skipped else ""
            lines.append(f"the tests measured {pairs - len(self.skipped)} of the {pairs} pairs, behind the "
                         f"poses{skipped}")
        return lines


def _listed(numbers: Sequence[int]) -> str:
    """The first ten ``numbers``, then ``...``."""
    return ", ".join(map(str, numbers[:10])) + (", ..." if len(numbers) > 10 else "")


def record_arrivals(records: Iterable[Record], name: str, size: tuple[int, int]) -> Iterator[Arrived]:
    """The frames of an external VO's ``records`` (``dpc_jax.data.records``) of the file or stream
    ``name``, as they come, numbered from 0; each loads its images, checked to be ``size`` = ``(H, W)``,
    and the record's pose: ``(left, right, pose [4, 4])``."""
    for k, record in enumerate(records):
        where = f"{name} line {record.line}"

        def load(record: Record = record, where: str = where) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            return (record_image(record.left, size, where, "left"),
                    record_image(record.right, size, where, "right"), record.pose)

        yield Arrived(k, record.time_s, where, load)


def prior_arrivals(sequence: StereoSequence, prior: np.ndarray) -> Iterator[Arrived]:
    """The frames of an opened ``sequence`` (a recording's) as they come, numbered by their index in it;
    each loads its colour pair and its pose of an external VO's ``prior`` ``[N, 4, 4]``: ``(left, right,
    pose [4, 4])``, as :func:`record_arrivals`."""
    for frame in sequence.images.stream(sequence.image_size):
        def load(frame: Any = frame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            left, right = frame.decode()
            return left, right, prior[frame.index]

        yield Arrived(frame.index, float(sequence.times[frame.index]), frame.where, load)


def sequence_arrivals(sequence: StereoSequence, first: int, decoder: Executor) -> Iterator[Arrived]:
    """The frames of an opened ``sequence`` whose frame 0 is the source's frame ``first``, as they come;
    each loads its four images, decoded a pair at a time on ``decoder``: the colour pair (the network's)
    and the grey one, decoded as ``dpc-jax vo`` decodes it, so that :class:`VOStep`'s prior is its
    trajectory."""
    for frame in sequence.images.stream(sequence.image_size):
        def load(frame: Any = frame) -> list[np.ndarray]:
            jobs = [decoder.submit(frame.decode, grey) for grey in (False, True)]
            return [image for job in jobs for image in job.result()]

        k = frame.index
        yield Arrived(first + k, float(sequence.times[k]), f"{sequence.name} frame {first + k}", load)


class VOStep:
    """The step of a stream whose prior is our VO (``dpc-jax vo --correct``): per frame, the VO's pose
    from the grey pair, then the ``live`` corrector's from the colour pair and that pose (the images of
    :func:`sequence_arrivals`); the prior starts at ``start`` ``[4, 4]``. Keeps per pair what the VO's own
    summary needs (:meth:`result`, as ``dpc_jax.vo.run_vo`` gives it) and per frame the corrected poses
    (:attr:`corrected`)."""

    def __init__(self, vo: StereoVO, live: LiveCorrector, start: np.ndarray) -> None:
        self.vo, self.live, self.start = vo, live, start
        self.kept: dict[str, list[Any]] = {k: [] for k in ("relative", "inliers", "status", "times", "offset",
                                                           "prior", "corrected")}
        self.first_s = 0.0  # the VO's time on frame 0, which has no pair

    def __call__(self, images: list[np.ndarray]) -> Corrected:
        kept = self.kept
        vo: dict[str, Any] = {}

        def prior() -> np.ndarray:  # called by the corrector (behind, while it prepares the pair)
            t = time.perf_counter()
            estimate = self.vo.process(images[2], images[3])
            vo["s"] = time.perf_counter() - t
            if estimate is None:
                vo["pose"], vo["columns"] = self.start, None
                self.first_s = vo["s"]  # counted with the first pair, as `dpc-jax vo` does
                return self.start
            vo["pose"] = kept["prior"][-1] @ np.linalg.inv(estimate.relative)
            vo["columns"] = (estimate.inliers, estimate.status.name.lower(), self.vo.disparity_offset)
            for key, value in (("relative", estimate.relative), ("inliers", estimate.inliers),
                               ("status", int(estimate.status)), ("offset", self.vo.disparity_offset),
                               ("times", vo["s"] + (0.0 if kept["times"] else self.first_s))):
                kept[key].append(value)
            return vo["pose"]

        # The prior written is the VO's own chain of poses, as `dpc-jax vo` composes it: the corrector's
        # prior, recomposed from its first pose, differs from it in the last digits (1e-13).
        frame = self.live(images[0], images[1], prior)
        frame = dataclasses.replace(frame, prior=vo["pose"])
        kept["prior"].append(vo["pose"])
        kept["corrected"].append(frame.pose)
        return Corrected(frame, vo["columns"], vo["s"])

    def result(self) -> VOResult:
        """The VO's result over the frames stepped (its poses the prior's)."""
        from dpc_jax.vo import VOResult

        kept = self.kept
        return VOResult(
            poses=np.stack(kept["prior"]), relative=np.stack(kept["relative"]),
            inliers=np.asarray(kept["inliers"], np.int64), status=np.asarray(kept["status"], np.int8),
            times=np.asarray(kept["times"]), disparity_offset=np.asarray(kept["offset"]))

    @property
    def corrected(self) -> np.ndarray:
        """``[N, 4, 4]`` the corrected poses of the frames stepped."""
        return np.stack(self.kept["corrected"])


def correct_frames(
    frames: Iterator[Arrived], step: Callable[[Any], Corrected], outputs: LiveOutputs, summary: LiveSummary,
    on_arrival: Callable[[], None] | None = None,
) -> None:
    """Correct each frame as it arrives and write it (module docstring).

    ``frames``: the source, which blocks until the next frame is there (a stream) or gives it at once
    (a recording); ``step``: the frame's loaded images → its correction. With ``summary.pace`` frame k
    is due ``pace.due(k)`` s after the first arrived (the command sleeps until then) and misses its
    deadline when its pose is written after frame k+1 is due; else it arrives when the source gives it. A
    frame that cannot be loaded or corrected (``ValueError``, ``OSError``) raises :class:`RecordError`
    with the frame's name (``where``) in front. ``on_arrival``: called the moment a frame arrives, before its
    images are read (``LiveCorrector.hold``: the measurement behind the poses stops for the frame).
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
        if on_arrival is not None:
            on_arrival()
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
            lines = (kitti_line(corrected.frame.pose), kitti_line(corrected.frame.prior))
            written = outputs.write(lines, row)
            summary.add(arrived.number, corrected, read_s, written - arrival, written > due)


def frame_state(frame: LiveFrame) -> str:
    """The ``state`` column of the live table: ``start`` (the first frame), ``forced``, ``prior`` (nothing
    applied) or the part applied (``frame.part``)."""
    if frame.index == 0:
        return "start"
    return "forced" if frame.forced else "prior" if frame.part == "none" else frame.part


def _row(arrived: Arrived, corrected: Corrected, read_s: float, arrival_s: float, started: float, due: float,
         paced: bool, written: float) -> str:
    """The CSV row (:data:`CSV_COLUMNS`) of a frame that arrived ``arrival_s`` s after the first,
    its poses written at the clock's ``written`` (the first frame arrived at ``started``), due ``due``
    (``paced``: under a pace, which gives the ``missed`` column)."""
    frame = corrected.frame
    inliers, status, offset = corrected.vo if corrected.vo is not None else ("", "", None)
    cells = [arrived.number, "" if arrived.time_s is None else f"{arrived.time_s:.6f}", frame_state(frame),
             ";".join(frame.events), inliers, status, "" if offset is None else f"{offset:.4f}", _ms(read_s),
             _ms(corrected.vo_s), *(_ms(frame.seconds.get(stage)) for stage in CORRECTION_STAGES),
             _ms(written - started - arrival_s), f"{arrival_s:.6f}", f"{written - started:.6f}",
             "" if not paced else int(written > due), "" if frame.index == 0 else int(frame.measured)]
    return ",".join(map(str, cells)) + "\n"


def _ms(seconds: float | None) -> str:
    return "" if seconds is None else f"{1e3 * seconds:.3f}"


def live_outputs(out: Path, prior: Path | None, csv: Path | None, *, stale: Sequence[Path | None] = (),
                 beside: Sequence[Path | None] = ()) -> LiveOutputs:
    """The outputs :func:`correct_frames` writes: the corrected poses ``out``, the prior's ``prior`` and
    the per-frame ``csv`` (None: not written); ``stale`` and ``beside`` as ``dpc_jax._io.LiveOutputs``."""
    return LiveOutputs((out, prior), csv, CSV_COLUMNS, stale=stale, beside=beside)


def network_words(live: LiveCorrector, run: Path) -> str:
    """``RUN (stereo_dpc, epoch 3, 64x96, judged at 240x376)``: the network of a live corrector and its
    judge, in words."""
    h, w = live.size
    judge = "" if live.judge_size is None else ", judged at {}x{}".format(*live.judge_size)
    return f"{run} ({live.run.config.method}, epoch {live.run.epoch}, {h}x{w}{judge})"


def write_summary(path: Path | None, record: dict[str, Any]) -> None:
    """The summary ``record`` as JSON at ``path`` (None: beside a stream, not made), atomically."""
    if path is not None:
        atomic_write(path, json.dumps(record, indent=2) + "\n")
