"""The outputs of a corrected sequence (``dpc_jax.correction.outputs.write_corrected``): the trajectory
and its frame list, the report, all or nothing; read back with the project's readers and numpy."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dpc_jax._io import foreign_files_problem
from dpc_jax.correction.corrector import CorrectedSequence
from dpc_jax.correction.outputs import (
    REPORT_FILES,
    REPORT_WRITER,
    CorrectionOutputs,
    adapted_path,
    write_corrected,
)
from dpc_jax.data.poses_io import read_kitti_poses, read_tum
from dpc_jax.results.acceptance import Acceptance
from dpc_jax.results.correction import Correction


def _done(frames: list[int]) -> CorrectedSequence:
    """A sequence of ``len(frames)`` poses (source ``frames``) corrected by a known trajectory."""
    rng = np.random.default_rng(0)
    n = len(frames)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.1, (n, 3))).as_matrix()
    poses[:, :3, 3] = rng.normal(0, 5.0, (n, 3))
    prior = np.tile(np.eye(4), (n, 1, 1))
    correction = Correction("05", np.asarray(frames), np.arange(n) * 0.1, prior, poses, poses, None,
                            np.zeros((n - 1, 6)), False, Acceptance(0.01, component="full"), 3, None)
    return CorrectedSequence(correction, None, None, "trained", correction)


def test_the_trajectory_its_frame_list_and_the_report_are_written(tmp_path: Path) -> None:
    done = _done([0, 2, 3, 7])
    out, report = tmp_path / "new" / "c.txt", tmp_path / "report"
    written = write_corrected(done, CorrectionOutputs(out, report=report, adapted=adapted_path(out)))
    assert written == [out, tmp_path / "new" / "c.frames.txt"]
    np.testing.assert_allclose(read_kitti_poses(out), done.result.corrected, atol=1e-9)
    assert (tmp_path / "new" / "c.frames.txt").read_text() == "0\n2\n3\n7\n"
    assert {"report.md", "summary.json"} <= {p.name for p in report.iterdir()}
    # Recorded as the command's own: a later run may replace them, and nothing else was adapted.
    assert foreign_files_problem(report, REPORT_FILES, "r", writer=REPORT_WRITER) is None
    assert not adapted_path(out).exists()


def test_tum_takes_the_frame_times_and_all_source_frames_need_no_list(tmp_path: Path) -> None:
    done = _done([0, 1, 2])
    out = tmp_path / "c.tum"
    assert write_corrected(done, CorrectionOutputs(out, "tum")) == [out]
    times, poses = read_tum(out)
    np.testing.assert_allclose(times, [0.0, 0.1, 0.2])
    np.testing.assert_allclose(poses, done.result.corrected, atol=1e-9)


def test_nothing_is_written_when_one_output_fails(tmp_path: Path) -> None:
    """The report's place is a file: the trajectory staged before it is not left behind."""
    blocked = tmp_path / "report"
    blocked.write_text("mine\n")
    with pytest.raises(OSError):
        write_corrected(_done([0, 2, 3]), CorrectionOutputs(tmp_path / "c.txt", report=blocked))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]
    assert blocked.read_text() == "mine\n"


def test_the_adapted_network_goes_beside_the_trajectory() -> None:
    assert adapted_path(Path("out/corrected.txt")) == Path("out/corrected.adapted")
    assert adapted_path("c.mcap") == Path("c.adapted")
