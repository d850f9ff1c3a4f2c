"""KITTI readers on generated odometry-layout fixtures and on the real raw excerpt."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import DATA
from support import BASELINE_COLOUR, BASELINE_GREY, CU, CV, FU, FV, write_odometry

from dpc_jax.data.kitti import load_image, open_odometry, open_raw

RAW = DATA / "kitti-raw"
RAW_MAT = RAW / "libviso2" / "stereo_2011_09_26_drive_0001.mat"


@pytest.fixture
def odometry(tmp_path: Path) -> tuple[Path, dict]:
    return tmp_path, write_odometry(tmp_path)


def test_odometry_colour_and_grey_pairs(odometry: tuple[Path, dict]) -> None:
    root, written = odometry
    seq = open_odometry(root, 0)
    assert seq.name == "00" and len(seq) == 6 and seq.image_size == (20, 32)
    np.testing.assert_allclose(seq.K, [[FU, 0, CU], [0, FV, CV], [0, 0, 1]])
    assert seq.baseline == pytest.approx(BASELINE_COLOUR, abs=1e-12)
    np.testing.assert_allclose(seq.times, written["times"])
    np.testing.assert_allclose(seq.poses, written["poses"], atol=1e-10)
    assert [p.name for p in seq.images.left_paths] == [f"{k:06d}.png" for k in range(6)]
    files = seq.images
    assert files.left_paths[0].parent.name == "image_2" and files.right_paths[0].parent.name == "image_3"
    np.testing.assert_array_equal(load_image(seq.images.left_paths[3]), written["images"][2][3])
    np.testing.assert_array_equal(load_image(seq.images.right_paths[5]), written["images"][3][5])

    grey = open_odometry(root, "00", grey=True)
    assert grey.baseline == pytest.approx(BASELINE_GREY, abs=1e-12)
    assert grey.images.left_paths[0].parent.name == "image_0"
    np.testing.assert_array_equal(load_image(grey.images.right_paths[2], grey=True), written["images"][1][2])


def test_select_frame_range(odometry: tuple[Path, dict]) -> None:
    root, written = odometry
    part = open_odometry(root, "00").select(2, 5)
    assert [p.name for p in part.images.left_paths] == ["000002.png", "000003.png", "000004.png"]
    np.testing.assert_allclose(part.poses, written["poses"][2:5], atol=1e-10)
    with pytest.raises(ValueError, match=r"frame range \[4, 9\)"):
        open_odometry(root, "00").select(4, 9)


def test_missing_sequence_poses_is_none(tmp_path: Path) -> None:
    write_odometry(tmp_path, name="03")
    (tmp_path / "poses" / "03.txt").unlink()
    assert open_odometry(tmp_path, 3).poses is None


def test_gap_in_frame_numbering(odometry: tuple[Path, dict]) -> None:
    root, _ = odometry
    (root / "sequences/00/image_2/000003.png").unlink()
    expected = r"image_2: gap in frame numbering: expected frame 3 .* found 000004\.png"
    with pytest.raises(ValueError, match=expected):
        open_odometry(root, "00")


def test_left_right_count_mismatch(odometry: tuple[Path, dict]) -> None:
    root, _ = odometry
    (root / "sequences/00/image_3/000005.png").unlink()
    with pytest.raises(ValueError, match=r"image_2 holds 6 frames but .*image_3 holds 5"):
        open_odometry(root, "00")


def test_poses_of_other_length(odometry: tuple[Path, dict]) -> None:
    root, written = odometry
    path = root / "poses" / "00.txt"
    np.savetxt(path, written["poses"][:5, :3, :].reshape(5, 12))
    with pytest.raises(ValueError, match=r"00\.txt: 5 poses for 6 frames"):
        open_odometry(root, "00")


def test_times_of_other_length(odometry: tuple[Path, dict]) -> None:
    root, _ = odometry
    (root / "sequences/00/times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(ValueError, match=r"times\.txt: 2 times for 6 frames"):
        open_odometry(root, "00")


def test_non_rigid_pose_names_file_and_line(odometry: tuple[Path, dict]) -> None:
    root, written = odometry
    bad = written["poses"].copy()
    bad[2, :3, :3] *= 1.2
    np.savetxt(root / "poses" / "00.txt", bad[:, :3, :].reshape(6, 12))
    with pytest.raises(ValueError, match=r"00\.txt.*line 3"):
        open_odometry(root, "00")


def test_calibration_missing_key(odometry: tuple[Path, dict]) -> None:
    root, _ = odometry
    calib = root / "sequences/00/calib.txt"
    kept = [line for line in calib.read_text().splitlines() if not line.startswith("P3")]
    calib.write_text("\n".join(kept) + "\n")
    with pytest.raises(ValueError, match=r"calib\.txt: calibration key 'P3' missing"):
        open_odometry(root, "00")
    open_odometry(root, "00", grey=True)  # the grey pair does not need P3


def test_calibration_malformed_row(odometry: tuple[Path, dict]) -> None:
    root, _ = odometry
    calib = root / "sequences/00/calib.txt"
    lines = calib.read_text().splitlines()
    lines[2] = "P2: 1 2 3"
    calib.write_text("\n".join(lines))
    with pytest.raises(ValueError, match=r"calib\.txt, line 3: P2 must hold 12 numbers, got 3"):
        open_odometry(root, "00")


def test_truncated_and_missing_png(odometry: tuple[Path, dict], tmp_path: Path) -> None:
    root, _ = odometry
    path = root / "sequences/00/image_2/000001.png"
    path.write_bytes(path.read_bytes()[:60])
    with pytest.raises(ValueError, match=r"000001\.png: cannot decode"):
        load_image(path)
    with pytest.raises(FileNotFoundError, match=r"nothing\.png"):
        load_image(tmp_path / "nothing.png")


def test_real_raw_excerpt() -> None:
    seq = open_raw(RAW, "2011_09_26", 1, poses=RAW_MAT)
    assert seq.name == "2011_09_26_drive_0001"
    assert len(seq) == 108 and len(seq.images.right_paths) == 108
    assert seq.image_size == (375, 1242)
    # README: fu = fv = 721.5377, cu = 609.5593, cv = 172.854, baseline ≈ 0.532 m.
    np.testing.assert_allclose(seq.K, [[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1]])
    assert seq.baseline == pytest.approx((4.485728e01 + 3.395242e02) / 721.5377, rel=1e-12)
    assert seq.times[0] == 0.0 and np.all(np.diff(seq.times) > 0.09) and np.all(np.diff(seq.times) < 0.12)
    assert seq.poses.shape == (108, 4, 4)
    steps = np.linalg.norm(np.diff(seq.poses[:, :3, 3], axis=0), axis=1)
    assert 100 < steps.sum() < 115  # README: about 107 m
    image = load_image(seq.images.left_paths[0])
    assert image.shape == (375, 1242, 3) and image.dtype == np.uint8
    # cv2 reads BGR; the reader must return RGB.
    np.testing.assert_array_equal(image[..., ::-1], cv2.imread(str(seq.images.left_paths[0])))


def test_raw_ground_truth_of_wrong_length() -> None:
    with pytest.raises(ValueError, match=r"ground truth: 10 poses for 108 frames"):
        open_raw(RAW, "2011_09_26", "0001", poses=np.tile(np.eye(4), (10, 1, 1)))
    with pytest.raises(FileNotFoundError, match="drive_0002_sync"):
        open_raw(RAW, "2011_09_26", 2)


RAW_MAT_0005 = RAW / "libviso2" / "stereo_2011_09_26_drive_0005.mat"


def _calibration_row(key: str) -> np.ndarray:
    """``key``'s 12 numbers parsed here independently of the reader."""
    for line in (RAW / "2011_09_26" / "calib_cam_to_cam.txt").read_text().splitlines():
        if line.startswith(f"{key}:"):
            return np.array(line.split(":", 1)[1].split(), dtype=np.float64).reshape(3, 4)
    raise AssertionError(f"{key} not in the calibration file")


def test_real_raw_grey_pair_of_drive_0005() -> None:
    from dpc_jax.data.kitti import read_ground_truth

    gt = read_ground_truth(RAW_MAT_0005)[:91]  # README: the first 91 of 154 poses belong to the images
    seq = open_raw(RAW, "2011_09_26", 5, poses=gt)  # auto: the drive holds only its grey pair
    assert seq.name == "2011_09_26_drive_0005" and len(seq) == 91 == len(seq.images.right_paths)
    files = seq.images
    assert files.left_paths[0].parts[-3] == "image_00" and files.right_paths[0].parts[-3] == "image_01"
    assert seq.image_size == (375, 1242)
    p0, p1 = _calibration_row("P_rect_00"), _calibration_row("P_rect_01")
    np.testing.assert_array_equal(seq.K, p0[:, :3])
    assert seq.baseline == pytest.approx((p0[0, 3] - p1[0, 3]) / p0[0, 0], rel=1e-12)
    assert seq.baseline == pytest.approx(0.537, abs=0.002)  # README: ≈ 0.54 m
    assert seq.times[0] == 0.0 and np.all(np.diff(seq.times) > 0.09) and np.all(np.diff(seq.times) < 0.12)
    length = np.linalg.norm(np.diff(seq.poses[:, :3, 3], axis=0), axis=1).sum()
    assert 30 < length < 38  # README: about 34 m
    # Grey PNGs enter every colour consumer as three equal channels (the network sees replicated grey).
    image = load_image(seq.images.left_paths[0])
    reference = cv2.imread(str(seq.images.left_paths[0]), cv2.IMREAD_UNCHANGED)
    assert reference.ndim == 2 and image.shape == (375, 1242, 3)
    for c in range(3):
        np.testing.assert_array_equal(image[..., c], reference)
    np.testing.assert_array_equal(load_image(seq.images.right_paths[5], grey=True),
                                  cv2.imread(str(seq.images.right_paths[5]), cv2.IMREAD_UNCHANGED))
    assert open_raw(RAW, "2011_09_26", 5, cameras="grey").images.left_paths == seq.images.left_paths


def test_raw_pair_choice_and_missing_cameras(tmp_path: Path) -> None:
    colour = open_raw(RAW, "2011_09_26", 1)  # auto: the colour pair when the drive has it
    assert colour.images.left_paths[0].parts[-3] == "image_02"
    missing = r"drive_000{}_sync: the {} pair \(image_0{}/, image_0{}/\) is missing"
    with pytest.raises(ValueError, match=missing.format(5, "colour", 2, 3)):
        open_raw(RAW, "2011_09_26", 5, cameras="colour")
    with pytest.raises(ValueError, match=missing.format(1, "grey", 0, 1)):
        open_raw(RAW, "2011_09_26", 1, cameras="grey")
    with pytest.raises(ValueError, match="cameras must be one of"):
        open_raw(RAW, "2011_09_26", 1, cameras="rgb")
    (tmp_path / "2011_09_26" / "2011_09_26_drive_0009_sync" / "image_00").mkdir(parents=True)
    with pytest.raises(ValueError, match="drive_0009_sync: no stereo pair"):
        open_raw(tmp_path, "2011_09_26", 9)


@pytest.mark.parametrize("command", ["vo", "prepare"])
def test_cli_names_the_missing_grey_pair_in_one_line(command: str, tmp_path: Path, capsys) -> None:
    from dpc_jax.cli import main

    extra = {"vo": [], "prepare": ["--prior", str(RAW_MAT)]}[command]
    out = tmp_path / ("cache" if command == "prepare" else "out.txt")
    status = main([command, "--kitti-raw", str(RAW), "--date", "2011_09_26", "--drive", "1", "--grey",
                   "--out", str(out), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert status in (1, 2) and len(err) == 1, err
    assert "the grey pair (image_00/, image_01/) is missing" in err[0]
    assert not out.exists()
