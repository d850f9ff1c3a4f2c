"""experiments/studies/library_versions.py: the comparison's arithmetic on arrays and trajectories whose
differences are planted, so known (the measurement itself is OpenCV's and our VO's, tested elsewhere)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import load_script

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "studies" / "library_versions.py"


@pytest.fixture(scope="module")
def study():
    return load_script(SCRIPT)


def test_a_disparity_is_compared_in_pixels_where_both_matched(study) -> None:
    a = np.full((2, 3, 4), 160, np.int16)  # 10 px everywhere, in SGBM's 1/16 px
    a[0, 0, 0] = -16  # no match in either
    b = a.copy()
    b[1, 2, 3] += 24  # 1.5 px more
    b[0, 1, 1] = 0  # matched in A only: left out of the differences, counted apart
    found = study.difference(a, b, "disparity")
    compared = a.size - 2
    assert found["validity"] == 1 / a.size
    assert found["max"] == 1.5 and found["mean"] == pytest.approx(1.5 / compared)
    assert found["differ"] == pytest.approx(1 / compared)


def test_a_flow_difference_is_the_length_of_the_difference_vector(study) -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(2, 5, 6, 2)).astype(np.float32)
    b = a.copy()
    b[1, 4, 5] += np.float32([3.0, -4.0])
    found = study.difference(a, b, "flow")
    assert found["max"] == pytest.approx(5.0, abs=1e-5)
    assert found["mean"] == pytest.approx(found["max"] / (a.size // 2))
    assert found["differ"] == 1 / (a.size // 2) and "validity" not in found


def test_identical_products_and_trajectories_differ_by_exactly_nothing(study) -> None:
    images = np.arange(24, dtype=np.uint8).reshape(2, 3, 4)
    assert study.difference(images, images.copy(), "images") == {"differ": 0.0, "max": 0.0, "mean": 0.0}
    poses = np.tile(np.eye(4), (3, 1, 1))
    assert study.trajectory_gap(poses, poses.copy()) == (0.0, 0.0)
    with pytest.raises(ValueError, match="shapes"):
        study.difference(images, images[:1], "images")


def test_the_trajectory_gap_is_the_largest_distance_and_angle(study) -> None:
    a = np.tile(np.eye(4), (3, 1, 1))
    b = a.copy()
    b[1, :3, 3] = [0.0, 0.3, 0.4]
    angle = np.radians(0.25)  # about an arbitrary unit axis, closed form (Rodrigues)
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    b[2, :3, :3] = np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew
    position, degrees = study.trajectory_gap(a, b)
    assert position == pytest.approx(0.5) and degrees == pytest.approx(0.25, rel=1e-9)
