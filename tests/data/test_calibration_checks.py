"""Calibrations checked against the images they describe (issue 40): the principal point in the middle
half of the image, a focal length giving a plausible field of view for the width, and the raw layout's
``S_rect_XX`` equal to the image size. The cases are the issue's: KITTI's full-size ``P0``–``P3`` beside
small images, a ``P_rect`` halved by hand, an ``S_rect`` of another size."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from support import projection_row, write_odometry

from dpc_jax.cli import main
from dpc_jax.data.kitti import MAX_FOV_DEG, MIN_FOV_DEG, check_intrinsics, open_odometry, open_raw

# KITTI's rectified colour camera of 2011_09_26 (P_rect_02) and its image size.
KITTI_FU, KITTI_CU, KITTI_CV = 721.5377, 609.5593, 172.854
KITTI_SIZE = (375, 1242)
# KITTI odometry sequence 00's calib.txt: the four projection matrices of 1241×376 images.
KITTI_ODOMETRY_CALIB = """\
P0: 7.188560e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0
P1: 7.188560e+02 0 6.071928e+02 -3.861448e+02 0 7.188560e+02 1.852157e+02 0 0 0 1 0
P2: 7.188560e+02 0 6.071928e+02 4.538225e+01 0 7.188560e+02 1.852157e+02 -1.130887e-01 0 0 1 3.779761e-03
P3: 7.188560e+02 0 6.071928e+02 -3.372877e+02 0 7.188560e+02 1.852157e+02 2.369057e+00 0 0 1 4.915215e-03
"""


def _kitti_K(scale: float = 1.0) -> np.ndarray:
    """KITTI's K for images scaled by ``scale`` (pixel centres at integers)."""
    return np.array([[KITTI_FU * scale, 0.0, (KITTI_CU + 0.5) * scale - 0.5],
                     [0.0, KITTI_FU * scale, (KITTI_CV + 0.5) * scale - 0.5], [0.0, 0.0, 1.0]])


def test_intrinsics_fit_their_images_at_every_scale() -> None:
    check_intrinsics(_kitti_K(), KITTI_SIZE, "calib")
    # Resized to 120×188 with K scaled alike (as `prepare` stores it): still consistent.
    check_intrinsics(_kitti_K(188 / 1242), (57, 188), "calib")


@pytest.mark.parametrize("case, size, scale, needle", [
    ("full-size K beside 120x188 images", (120, 188), 1.0, "principal point cu = 609.559 px"),
    ("K halved beside full-size images", KITTI_SIZE, 0.5, "principal point cu = 304.53 px"),
    ("K doubled beside full-size images", KITTI_SIZE, 2.0, "principal point cu = 1219.62 px"),
])
def test_intrinsics_for_another_image_size_are_refused(
    case: str, size: tuple[int, int], scale: float, needle: str
) -> None:
    with pytest.raises(ValueError, match=r"^calib\.txt: P2: ") as error:
        check_intrinsics(_kitti_K(scale), size, "calib.txt: P2")
    assert needle in str(error.value) and "another size" in str(error.value), case
    assert "\n" not in str(error.value)


@pytest.mark.parametrize("fov_deg", [MIN_FOV_DEG / 2, (MAX_FOV_DEG + 180) / 2])
def test_a_focal_length_implausible_for_the_width_is_refused(fov_deg: float) -> None:
    width = 1242
    fu = width / (2 * np.tan(np.radians(fov_deg) / 2))  # the focal length of that field of view
    K = _kitti_K()
    K[0, 0] = fu
    with pytest.raises(ValueError, match=rf"focal length fu = {fu:.6g} px gives a horizontal field of view "
                                         rf"of {fov_deg:.0f}°"):
        check_intrinsics(K, KITTI_SIZE, "calib.txt: P2")


def test_odometry_calib_of_full_size_images_beside_small_images(tmp_path: Path) -> None:
    """The issue's case: KITTI's P0–P3 in the calib.txt of 120×188 images (vo ran; m-ATE 90 m)."""
    write_odometry(tmp_path, n=3, size=(120, 188))
    calib = tmp_path / "sequences" / "00" / "calib.txt"
    open_odometry(tmp_path, "00")  # the fixture's own calibration fits
    calib.write_text(KITTI_ODOMETRY_CALIB)
    with pytest.raises(ValueError, match=rf"^{calib}: P2: principal point cu = 607.193 px, but the images "
                                         "are 188 px wide"):
        open_odometry(tmp_path, "00")
    with pytest.raises(ValueError, match=rf"^{calib}: P0: principal point cu = 607.193 px"):
        open_odometry(tmp_path, "00", grey=True)


def test_vo_refuses_the_calibration_in_one_line_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    write_odometry(tmp_path / "kitti", n=3, size=(120, 188))
    calib = tmp_path / "kitti" / "sequences" / "00" / "calib.txt"
    calib.write_text(KITTI_ODOMETRY_CALIB)
    out = tmp_path / "vo" / "00.txt"
    assert main(["vo", "--kitti-odometry", str(tmp_path / "kitti"), "--sequence", "00", "--out", str(out),
                 "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith(f"dpc-jax vo: error: {calib}: P2: principal point cu = 607.193")
    assert not (tmp_path / "vo").exists()


# ----------------------------------------------------------------------------- raw layout


DATE = "2011_09_26"
RAW_SIZE = (20, 32)  # H, W of the tiny drive
FU, CU, CV = 25.0, 15.5, 9.5


def _write_raw(root: Path, calib_rows: dict[str, str], n: int = 3) -> Path:
    """A tiny raw drive (colour pair, ``n`` frames of ``RAW_SIZE``) whose calib_cam_to_cam.txt holds
    ``calib_rows``; returns the calibration file."""
    drive = root / DATE / f"{DATE}_drive_0001_sync"
    rng = np.random.default_rng(0)
    for cam in ("image_02", "image_03"):
        (drive / cam / "data").mkdir(parents=True)
        for k in range(n):
            image = rng.integers(0, 256, (*RAW_SIZE, 3), dtype=np.uint8)
            assert cv2.imwrite(str(drive / cam / "data" / f"{k:010d}.png"), image)
    stamps = "".join(f"{DATE.replace('_', '-')} 13:02:25.{k:09d}\n" for k in range(n))
    (drive / "image_02" / "timestamps.txt").write_text(stamps)
    calib = root / DATE / "calib_cam_to_cam.txt"
    calib.write_text("".join(f"{key}: {value}\n" for key, value in calib_rows.items()))
    return calib


def _rows(scale: float = 1.0, s_rect: tuple[int, int] | None = (32, 20)) -> dict[str, str]:
    """P_rect_02/03 of the tiny drive scaled by ``scale``, with S_rect_02/03 ``(W, H)`` when given."""
    fu, cu, cv = FU * scale, (CU + 0.5) * scale - 0.5, (CV + 0.5) * scale - 0.5
    rows = {}
    for cam, tx in (("02", 0.06 * fu), ("03", -0.48 * fu)):
        if s_rect is not None:
            rows[f"S_rect_{cam}"] = f"{s_rect[0]:.6e} {s_rect[1]:.6e}"
        rows[f"P_rect_{cam}"] = projection_row(fu, cu, fu, cv, tx)
    return rows


def test_raw_calibration_that_fits_is_read(tmp_path: Path) -> None:
    _write_raw(tmp_path, _rows())
    sequence = open_raw(tmp_path, DATE, 1)
    np.testing.assert_allclose(sequence.K, [[FU, 0, CU], [0, FU, CV], [0, 0, 1]])
    assert sequence.image_size == RAW_SIZE and sequence.baseline == pytest.approx(0.54)
    _write_raw(tmp_path / "no_s_rect", _rows(s_rect=None))  # S_rect is checked only where given
    assert open_raw(tmp_path / "no_s_rect", DATE, 1).image_size == RAW_SIZE


def test_raw_p_rect_halved_is_refused(tmp_path: Path) -> None:
    """The issue's case: P_rect_02/03 halved in the date folder (m-ATE 40.3 m instead of 0.245 m)."""
    calib = _write_raw(tmp_path, _rows(scale=0.5))
    with pytest.raises(ValueError, match=rf"^{calib}: P_rect_02: principal point cu = 7.5 px, but the "
                                         r"images are 32 px wide; expected 8 to 24"):
        open_raw(tmp_path, DATE, 1)


def test_raw_s_rect_of_another_size_is_refused(tmp_path: Path) -> None:
    """The issue's case: an S_rect_02 of half the size beside full-size images was ignored."""
    rows = _rows()
    rows["S_rect_02"] = f"{16:.6e} {10:.6e}"
    calib = _write_raw(tmp_path, rows)
    line = list(rows).index("S_rect_02") + 1
    with pytest.raises(ValueError, match=rf"^{calib}, line {line}: S_rect_02 is 16x10 \(width x height\) but "
                                         r"the images are 32x20; P_rect_02 describes images of another size"):
        open_raw(tmp_path, DATE, 1)
