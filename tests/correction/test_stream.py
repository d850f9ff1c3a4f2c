"""``dpc_jax.correction.stream``: the live loop around a corrector, with a step that needs no network:
each frame's poses and CSV row written as it is stepped, a frame that cannot be loaded, a paced replay's
deadlines, and a run that steps no frame."""

from __future__ import annotations

import csv
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from dpc_jax.correction.stream import (
    CSV_COLUMNS,
    Arrived,
    Corrected,
    LiveSummary,
    Pace,
    correct_frames,
    live_outputs,
)
from dpc_jax.data.records import RecordError
from dpc_jax.geometry.poses import validate_poses


def _poses(n: int, seed: int) -> np.ndarray:
    """``[n, 4, 4]`` rigid poses with full-precision values (a rotation about z and a translation)."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for k, (angle, *t) in enumerate(rng.uniform(-3.0, 3.0, (n, 4))):
        c, s = np.cos(angle), np.sin(angle)
        poses[k, :2, :2] = [[c, -s], [s, c]]
        poses[k, :3, 3] = t
    return validate_poses(poses, "poses")


def _read(path: Path) -> np.ndarray:
    """KITTI pose rows as ``[N, 4, 4]``, read by numpy (the project's reader re-projects rotations)."""
    rows = np.loadtxt(path, ndmin=2).reshape(-1, 3, 4)
    return np.concatenate([rows, np.tile([[[0.0, 0.0, 0.0, 1.0]]], (len(rows), 1, 1))], axis=1)


def _frames(n: int, fail_at: int | None = None, slow_at: int | None = None) -> list[Arrived]:
    def load(k: int) -> int:
        if k == fail_at:
            raise OSError(f"image {k}.png: cannot be read")
        if k == slow_at:
            time.sleep(0.25)
        return k

    return [Arrived(10 + k, 0.1 * k, f"frame {10 + k}", lambda k=k: load(k)) for k in range(n)]


def _step(poses: np.ndarray, priors: np.ndarray) -> Callable[[int], Corrected]:
    def step(k: int) -> Corrected:
        events = ("rotation accepted",) if k == 2 else ()
        # What the loop reads of a LiveFrame, without a network: nothing applied yet; pair 3 not measured.
        frame = SimpleNamespace(index=k, pose=poses[k], prior=priors[k], part="none", forced=False,
                                events=events, seconds={"network": 1e-3}, measured=k != 3)
        return Corrected(frame)  # type: ignore[arg-type]

    return step


def test_each_frame_is_written_whole_with_its_row_and_counted(tmp_path: Path) -> None:
    poses, priors = _poses(5, 0), _poses(5, 1)
    out, prior, table = tmp_path / "a" / "live.txt", tmp_path / "a" / "live.prior.txt", tmp_path / "live.csv"
    summary = LiveSummary(None, 0.5)
    with live_outputs(out, prior, table) as outputs:
        correct_frames(iter(_frames(5)), _step(poses, priors), outputs, summary)
    # Read back with numpy's own text reader: the same float64 values, bit for bit.
    np.testing.assert_array_equal(_read(out), poses)
    np.testing.assert_array_equal(_read(prior), priors)
    with table.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert tuple(rows[0]) == CSV_COLUMNS
    columns = ("frame", "time_s", "state", "events", "network_ms", "missed", "measured")
    assert [tuple(r[c] for c in columns) for r in rows] == [
        (str(10 + k), f"{0.1 * k:.6f}", "start" if k == 0 else "prior", "rotation accepted" if k == 2 else "",
         "1.000", "", "" if k == 0 else str(int(k != 3))) for k in range(5)]
    assert summary.frames == 5 and dict(summary.states) == {"start": 1, "prior": 4}
    assert summary.events == [(12, "rotation accepted")]
    assert summary.record()["missed_deadlines"] is None and summary.record()["skipped_pairs"] == [13]


def test_a_frame_that_cannot_be_loaded_ends_the_run_after_the_frames_before_it(tmp_path: Path) -> None:
    poses = _poses(4, 2)
    out, table = tmp_path / "live.txt", tmp_path / "live.csv"
    summary = LiveSummary(None, 0.0)
    with pytest.raises(RecordError, match=r"^frame 12: image 2.png: cannot be read$"), \
            live_outputs(out, None, table) as outputs:
        correct_frames(iter(_frames(4, fail_at=2)), _step(poses, poses), outputs, summary)
    np.testing.assert_array_equal(_read(out), poses[:2])
    assert len(table.read_text().splitlines()) == 1 + 2 and summary.frames == 2


def test_a_paced_frame_written_after_the_next_one_is_due_misses_its_deadline(tmp_path: Path) -> None:
    """At 5 Hz frame k is due 0.2·k s after the first; a frame that takes 0.25 s to load is written after
    the next one is due. (The others are not checked: a loaded machine may make them late too.)"""
    poses = _poses(3, 3)
    summary = LiveSummary(Pace(5.0), 0.0)
    table = tmp_path / "live.csv"
    with live_outputs(tmp_path / "live.txt", None, table) as outputs:
        correct_frames(iter(_frames(3, slow_at=1)), _step(poses, poses), outputs, summary)
    assert 11 in summary.missed
    rows = list(csv.DictReader(table.open(newline="")))
    assert [float(r["arrival_s"]) for r in rows] == pytest.approx([0.0, 0.2, 0.4], abs=0.02)
    assert rows[1]["missed"] == "1"
    assert summary.lines()[-2].startswith(f"realtime 5 Hz: {len(summary.missed)} of 3 frames missed")
    assert summary.lines()[-1] == "the tests measured 2 of the 2 pairs, behind the poses"


def test_a_pace_of_own_times_is_due_at_each_frames_time_and_the_last_never() -> None:
    pace = Pace(None, np.array([100.0, 100.1, 100.35]))
    assert [pace.due(k) for k in range(4)] == pytest.approx([0.0, 0.1, 0.35, np.inf])
    assert Pace(10.0).due(3) == pytest.approx(0.3)


def test_a_run_that_steps_no_frame_leaves_every_file_as_it_was(tmp_path: Path) -> None:
    stale = tmp_path / "live.json"
    stale.write_text("an earlier run's summary\n")
    with live_outputs(tmp_path / "live.txt", None, tmp_path / "live.csv", stale=(stale,)) as outputs:
        correct_frames(iter(()), _step(_poses(1, 4), _poses(1, 4)), outputs, LiveSummary(None, 0.0))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["live.json"]
    assert stale.read_text() == "an earlier run's summary\n"
