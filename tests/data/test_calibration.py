"""``dpc_jax.load_calibration``: the stereo pair of a KITTI calibration file, K and the baseline against
the numbers of the file worked out by hand, the images' size from ``S_rect_XX`` or given, and the files
it cannot read refused naming them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import dpc_jax
from dpc_jax.data.calibration import NoImageSize, load_calibration

# The real drives' calib_cam_to_cam.txt: every P_rect_XX has fu = fv = 7.215377e+02, cu = 6.095593e+02,
# cv = 1.728540e+02; P[0, 3] is 0 (P_rect_00), -3.875744e+02 (01), 4.485728e+01 (02), -3.395242e+02 (03).
K_RAW = np.array([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]])
COLOUR_BASELINE = (44.85728 + 339.5242) / 721.5377  # 0.5327 m
GREY_BASELINE = 387.5744 / 721.5377  # 0.5372 m


@pytest.mark.parametrize("grey,baseline", [(False, COLOUR_BASELINE), (True, GREY_BASELINE)],
                         ids=["colour", "grey"])
def test_a_raw_drives_calibration_is_its_pairs_k_and_baseline(grey: bool, baseline: float) -> None:
    from conftest import DATA

    calibration = dpc_jax.load_calibration(DATA / "kitti-raw" / "2011_09_26" / "calib_cam_to_cam.txt",
                                           grey=grey)
    assert isinstance(calibration, dpc_jax.Calibration)
    np.testing.assert_array_equal(calibration.K, K_RAW)
    assert calibration.baseline == pytest.approx(baseline, rel=1e-12)
    assert calibration.image_size == (375, 1242)  # S_rect_XX: width 1242, height 375


def test_a_calib_txt_needs_the_images_size_and_is_refused_without_its_pair(tmp_path: Path) -> None:
    """An odometry calib.txt (P0–P3, no sizes): the size given; its grey pair missing is refused."""
    calib = tmp_path / "calib.txt"
    calib.write_text("P2: 500 0 160 40 0 500 120 0 0 0 1 0\n"
                     "P3: 500 0 160 -210 0 500 120 0 0 0 1 0\n")
    calibration = load_calibration(calib, image_size=(240, 320))
    np.testing.assert_array_equal(calibration.K, [[500, 0, 160], [0, 500, 120], [0, 0, 1]])
    assert calibration.baseline == pytest.approx(250 / 500, rel=1e-15)
    assert calibration.image_size == (240, 320)
    with pytest.raises(NoImageSize, match=r"does not give the images' size \(a calib.txt has none\)"):
        load_calibration(calib)
    grey_missing = r"calib.txt: no grey stereo pair; expected the keys P_rect_00/P_rect_01 or P0/P1"
    with pytest.raises(ValueError, match=grey_missing):
        load_calibration(calib, grey=True, image_size=(240, 320))
    with pytest.raises(FileNotFoundError, match="calibration file not found"):
        load_calibration(tmp_path / "none.txt", image_size=(240, 320))


def test_the_reader_is_light() -> None:
    """The command line reads a calibration before JAX starts."""
    code = "import sys, dpc_jax.data.calibration; print('jax' in sys.modules, 'flax' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]
