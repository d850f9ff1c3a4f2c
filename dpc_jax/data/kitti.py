"""Readers for the KITTI odometry and KITTI raw layouts (images, calibration, times, poses).

Both readers return a :class:`StereoSequence`: the file lists of a rectified stereo pair, the
intrinsics of its left camera, the baseline, the frame times and, when known, the ground-truth
poses. Nothing is decoded here except the first left image (for the image size); images are
read with :func:`load_image` when they are needed.

Layouts (docs/method.md §6):

* odometry: ``ROOT/sequences/XX/{image_2,image_3}/NNNNNN.png`` (grey: ``image_0``, ``image_1``),
  ``ROOT/sequences/XX/calib.txt`` (rows ``P0:`` … ``P3:``, 12 numbers each), ``times.txt`` (one
  time in seconds per line), and ground truth ``ROOT/poses/XX.txt`` when it exists.
* raw: ``ROOT/DATE/DATE_drive_NNNN_sync/image_0{2,3}/data/NNNNNNNNNN.png`` with
  ``ROOT/DATE/calib_cam_to_cam.txt`` (``P_rect_02``, ``P_rect_03``) and
  ``image_02/timestamps.txt``; the grey pair ``image_0{0,1}`` with ``P_rect_00``, ``P_rect_01`` and
  ``image_00/timestamps.txt``; ground truth from a pose file or a ``.mat`` file given by the caller.

The calibration is checked against the images (:func:`check_intrinsics`; ``S_rect_XX`` where the raw
layout gives it): one written for another image size gives a trajectory wrong by metres that looks fine.

Poses are used as the files give them (camera-to-world, docs/method.md §1). The odometry ground truth
and the ss-DPC-Net ``.mat`` files describe camera 0 (grey left); the colour pair's left camera
sits 6 cm to its side with the same orientation, which changes inter-frame translations by
``|(I − R) t|`` (millimetres at KITTI's rotation rates), so the offset is not applied, as in the
reference implementations.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dpc_jax.data import poses_io
from dpc_jax.data.frames import ImageFiles, StereoFrames, load_image
from dpc_jax.data.poses_io import validate_poses

# The horizontal fields of view a rectified stereo camera is believed to have (KITTI's colour pair:
# 81°): a narrower or wider one from the calibration means it was written for another image width.
MIN_FOV_DEG = 10.0
MAX_FOV_DEG = 150.0


@dataclass(frozen=True)
class StereoSequence:
    """A rectified stereo sequence on disk.

    * ``name``: identifier used for caches and reports (``"09"``, ``"2011_09_26_drive_0001"``).
    * ``images``: the N frames of the left and right camera (:class:`~dpc_jax.data.frames.ImageFiles`
      for the KITTI layouts).
    * ``K``: float64 ``[3, 3]`` intrinsics of the left camera in pixels of the stored images.
    * ``baseline``: metres; the right camera is at ``+baseline`` along x of the left camera.
    * ``image_size``: ``(H, W)`` of the stored images.
    * ``times``: float64 ``[N]`` seconds (from the first frame for the raw layout).
    * ``poses``: float64 ``[N, 4, 4]`` camera-to-world ground truth, or None when unknown.
    * ``sources``: the calibration, time and pose files read (their contents identify the inputs
      of a preprocessing cache together with the image files).
    """

    name: str
    images: StereoFrames
    K: np.ndarray
    baseline: float
    image_size: tuple[int, int]
    times: np.ndarray
    poses: np.ndarray | None = None
    sources: tuple[Path, ...] = field(default=())

    def __len__(self) -> int:
        return len(self.images)

    def select(self, start: int, stop: int) -> StereoSequence:
        """The frames ``start <= i < stop`` (Python slice bounds, validated) as a new sequence."""
        n = len(self)
        if not 0 <= start < stop <= n or stop - start < 2:
            raise ValueError(
                f"{self.name}: frame range [{start}, {stop}) must hold at least 2 of the {n} frames"
            )
        return replace(
            self,
            images=self.images.select(start, stop),
            times=self.times[start:stop],
            poses=None if self.poses is None else self.poses[start:stop],
        )


def _frame_files(directory: Path) -> tuple[Path, ...]:
    """The numbered PNGs of a camera folder, checked to be consecutive."""
    if not directory.is_dir():
        raise FileNotFoundError(f"{directory}: image folder not found")
    files = sorted(p for p in directory.iterdir() if p.suffix.lower() == ".png")
    if not files:
        raise ValueError(f"{directory}: no PNG images")
    numbers = []
    for p in files:
        if not re.fullmatch(r"\d+", p.stem):
            raise ValueError(f"{p}: expected a frame number as the file name (e.g. 000000.png)")
        numbers.append(int(p.stem))
    first = numbers[0]
    for k, number in enumerate(numbers):
        if number != first + k:
            raise ValueError(
                f"{directory}: gap in frame numbering: expected frame {first + k} after "
                f"{files[k - 1].name}, found {files[k].name}"
            )
    return tuple(files)


def _pair_files(left_dir: Path, right_dir: Path) -> tuple[tuple[Path, ...], tuple[Path, ...]]:
    left, right = _frame_files(left_dir), _frame_files(right_dir)
    if len(left) != len(right):
        raise ValueError(
            f"{left_dir} holds {len(left)} frames but {right_dir} holds {len(right)}: "
            "expected the same number of left and right frames"
        )
    for a, b in zip(left, right, strict=True):
        if a.name != b.name:
            raise ValueError(f"left frame {a} has no right counterpart {right_dir / a.name}")
    return left, right


def read_calibration(path: Path) -> dict[str, tuple[int, str]]:
    """Lines ``KEY: values`` of a KITTI calibration file as ``{key: (line number, values)}``."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: calibration file not found")
    entries: dict[str, tuple[int, str]] = {}
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        key, sep, values = line.partition(":")
        if not sep:
            raise ValueError(f"{path}, line {number}: expected 'KEY: values', got {line!r}")
        entries[key.strip()] = (number, values)
    return entries


def projection_matrix(entries: dict[str, tuple[int, str]], key: str, path: Path) -> np.ndarray:
    """The 3×4 projection matrix stored under ``key`` (12 numbers, row-major)."""
    if key not in entries:
        raise ValueError(f"{path}: calibration key {key!r} missing (expected a line '{key}: 12 numbers')")
    number, values = entries[key]
    try:
        flat = np.array([float(v) for v in values.split()], dtype=np.float64)
    except ValueError:
        raise ValueError(f"{path}, line {number}: {key} holds a non-numeric value") from None
    if flat.size != 12:
        raise ValueError(f"{path}, line {number}: {key} must hold 12 numbers, got {flat.size}")
    bad = np.flatnonzero(~np.isfinite(flat))
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"{path}, line {number}: {key} holds a value that is not finite ({flat[i]} at entry {i + 1} "
            "of 12); expected 12 finite numbers"
        )
    return flat.reshape(3, 4)


def stereo_calibration(
    path: Path, left_key: str, right_key: str, image_size: tuple[int, int]
) -> tuple[np.ndarray, float]:
    """``(K [3, 3], baseline m)`` of a rectified pair from its projection matrices in a KITTI calibration
    file (:func:`rectified_pair`); ``image_size`` ``(H, W)``: the stored images, which the calibration
    must fit (the raw layout's ``S_rect_XX`` too, where the file gives it).
    """
    entries = read_calibration(path)
    p_left = projection_matrix(entries, left_key, path)
    p_right = projection_matrix(entries, right_key, path)
    for key in (left_key, right_key):
        _check_rectified_size(entries, key, path, image_size)
    return rectified_pair(p_left, p_right, image_size, f"{path}: {left_key}", f"{path}: {right_key}")


def rectified_pair(
    p_left: np.ndarray, p_right: np.ndarray, image_size: tuple[int, int], left: str, right: str
) -> tuple[np.ndarray, float]:
    """``(K [3, 3], baseline m)`` of a rectified pair from its 3×4 projection matrices.

    ``K`` is the left 3×3 block; ``baseline = (P_left[0, 3] − P_right[0, 3]) / fu`` (docs/method.md §6;
    ROS's ``CameraInfo.P`` follows the same rule). ``image_size`` ``(H, W)``: the images, which the
    calibration must fit (:func:`check_intrinsics`). ``left``, ``right``: where each matrix was read
    (a file and key, a recording's topic), for the ``ValueError`` of one that is not a rectified pair.
    """
    K = p_left[:, :3].copy()
    fu = K[0, 0]
    if fu <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0:
        raise ValueError(f"{left} is not a pinhole projection [[fu,0,cu,·],[0,fv,cv,·],[0,0,1,·]]")
    if not np.allclose(p_left[:, :3], p_right[:, :3], rtol=1e-6, atol=1e-9):
        raise ValueError(f"{left} and {right} differ in K; expected a rectified pair")
    check_intrinsics(K, image_size, left)
    baseline = float((p_left[0, 3] - p_right[0, 3]) / fu)
    if baseline <= 0:
        raise ValueError(
            f"{left}, {right}: baseline (P_left[0,3] − P_right[0,3]) / fu = {baseline:.4g} m; expected > 0 "
            "(right camera to the right of the left one)"
        )
    return K, baseline


def check_intrinsics(K: np.ndarray, image_size: tuple[int, int], where: str) -> None:
    """Refuse intrinsics ``K`` that cannot belong to images of ``image_size`` ``(H, W)``.

    A calibration written for another resolution (KITTI's full-size ``P2`` beside downscaled images,
    a ``P_rect`` halved by hand) gives a trajectory that looks plausible and is wrong by metres, so
    it is caught here: the principal point must lie in the middle half of the image (a scaled
    calibration moves it towards a corner or out of the image; rectified cameras keep it near the
    centre) and ``fu`` must give a horizontal field of view between ``MIN_FOV_DEG`` and
    ``MAX_FOV_DEG``. ``ValueError`` naming ``where`` (the file and key) and the number.
    """
    height, width = image_size
    fu, cu, cv = float(K[0, 0]), float(K[0, 2]), float(K[1, 2])
    for name, value, extent, axis in (("cu", cu, width, "wide"), ("cv", cv, height, "high")):
        if not extent / 4 <= value <= 3 * extent / 4:
            raise ValueError(
                f"{where}: principal point {name} = {value:.6g} px, but the images are {extent} px {axis}; "
                f"expected {extent / 4:g} to {3 * extent / 4:g} (the middle half): is the calibration for "
                f"images of another size ({height}x{width} here)?"
            )
    fov = float(np.degrees(2.0 * np.arctan(width / (2.0 * fu))))
    if not MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
        raise ValueError(
            f"{where}: focal length fu = {fu:.6g} px gives a horizontal field of view of {fov:.0f}° for "
            f"images {width} px wide; expected {MIN_FOV_DEG:g}° to {MAX_FOV_DEG:g}°: is the calibration for "
            f"images of another size ({height}x{width} here)?"
        )


def _check_rectified_size(
    entries: dict[str, tuple[int, str]], key: str, path: Path, image_size: tuple[int, int]
) -> None:
    """The raw layout's ``S_rect_XX: W H`` (beside ``P_rect_XX``) must equal the images' size."""
    if not key.startswith("P_rect_"):
        return
    size_key = "S_rect_" + key.removeprefix("P_rect_")
    if size_key not in entries:
        return
    number, values = entries[size_key]
    try:
        width, height = (float(v) for v in values.split())
    except ValueError:
        raise ValueError(f"{path}, line {number}: {size_key} must hold 2 numbers (width height), "
                         f"got {values.strip()!r}") from None
    if (height, width) != (float(image_size[0]), float(image_size[1])):
        raise ValueError(
            f"{path}, line {number}: {size_key} is {width:g}x{height:g} (width x height) but the images are "
            f"{image_size[1]}x{image_size[0]}; {key} describes images of another size"
        )


def _read_times(path: Path, n: int) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: times file not found")
    values = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values.append(float(line))
        except ValueError:
            raise ValueError(f"{path}, line {number}: expected a time in seconds, got {line!r}") from None
    return _check_times(np.array(values, dtype=np.float64), path, n)


def _read_timestamps(path: Path, n: int) -> np.ndarray:
    """KITTI raw ``timestamps.txt`` (``YYYY-MM-DD hh:mm:ss.nnnnnnnnn``) as seconds since the first."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: timestamps file not found")
    stamps = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            stamps.append(np.datetime64(line.strip().replace(" ", "T"), "ns"))
        except ValueError:
            raise ValueError(
                f"{path}, line {number}: expected 'YYYY-MM-DD hh:mm:ss.fraction', got {line!r}"
            ) from None
    ns = np.array(stamps, dtype="datetime64[ns]")
    seconds = (ns - ns[0]).astype(np.int64) / 1e9 if ns.size else np.zeros(0)
    return _check_times(seconds, path, n)


def _check_times(times: np.ndarray, path: Path, n: int) -> np.ndarray:
    if times.size != n:
        raise ValueError(f"{path}: {times.size} times for {n} frames; expected one time per frame")
    bad = np.flatnonzero(~np.isfinite(times) | np.concatenate([[False], np.diff(times) < 0]))
    if bad.size:
        raise ValueError(f"{path}: time of frame {int(bad[0])} is not finite or goes backwards")
    return times


def _check_poses(poses: np.ndarray, n: int, source: str) -> np.ndarray:
    if poses.shape[0] != n:
        raise ValueError(f"{source}: {poses.shape[0]} poses for {n} frames; expected one pose per frame")
    return poses


def _image_size(path: Path) -> tuple[int, int]:
    image = load_image(path)
    return int(image.shape[0]), int(image.shape[1])


def open_odometry(root: str | Path, sequence: str | int, grey: bool = False) -> StereoSequence:
    """Open KITTI odometry sequence ``sequence`` (``"09"`` or ``9``) under ``root``.

    Colour pair ``image_2``/``image_3`` with ``P2``/``P3`` by default, grey pair
    ``image_0``/``image_1`` with ``P0``/``P1`` when ``grey``. Ground truth is read from
    ``root/poses/XX.txt`` when that file exists (None otherwise).
    """
    root = Path(root)
    name = f"{int(sequence):02d}" if str(sequence).isdigit() else str(sequence)
    # The name becomes a cache's folder name and a file name (vo's priors): a path would put them
    # elsewhere, after the images were read.
    problem = _name_problem(name, "sequence", root / "sequences", "05")
    if problem is not None:
        raise ValueError(problem)
    seq_dir = root / "sequences" / name
    if not seq_dir.is_dir():
        raise FileNotFoundError(f"{seq_dir}: odometry sequence folder not found")
    cams = (0, 1) if grey else (2, 3)
    left, right = _pair_files(seq_dir / f"image_{cams[0]}", seq_dir / f"image_{cams[1]}")
    calib_path = seq_dir / "calib.txt"
    image_size = _image_size(left[0])
    K, baseline = stereo_calibration(calib_path, f"P{cams[0]}", f"P{cams[1]}", image_size)
    times_path = seq_dir / "times.txt"
    times = _read_times(times_path, len(left))
    pose_path = root / "poses" / f"{name}.txt"
    sources = [calib_path, times_path]
    poses = None
    if pose_path.is_file():
        poses = _check_poses(poses_io.read_trajectory(pose_path, "kitti"), len(left), str(pose_path))
        sources.append(pose_path)
    return StereoSequence(
        name=name, images=ImageFiles(left, right), K=K, baseline=baseline,
        image_size=image_size, times=times, poses=poses, sources=tuple(sources),
    )


def _name_problem(name: str, what: str, folder: Path, example: str) -> str | None:
    """Why ``name`` is not the name of one folder in ``folder`` (empty, ``.``, ``..`` or a path), or None."""
    if name and name not in (".", "..") and "/" not in name and "\0" not in name:
        return None
    return (f"{what} {name!r}: expected the name of a folder in {folder} (such as {example}), not a path")


def read_ground_truth(source: str | Path, format: str | None = None) -> np.ndarray:
    """Ground-truth trajectory ``[N, 4, 4]`` from a pose file; for ``.mat`` its ``poses_gt``."""
    return poses_io.read_trajectory(source, format, mat_key="poses_gt")


RAW_CAMERAS = ("auto", "colour", "grey")
# The rectified pairs of the raw layout: (left folder, right folder, left key, right key).
_RAW_PAIRS = {"colour": ("image_02", "image_03", "P_rect_02", "P_rect_03"),
              "grey": ("image_00", "image_01", "P_rect_00", "P_rect_01")}


def raw_cameras(drive_dir: Path, cameras: str = "auto") -> str:
    """Which pair of a raw drive folder to read: ``colour`` (``image_02``/``image_03``) or ``grey``
    (``image_00``/``image_01``). ``auto`` takes the colour pair when both of its folders exist, else the
    grey pair; ``ValueError`` (one line naming the folder) when the asked pair is not there."""
    if cameras not in RAW_CAMERAS:
        raise ValueError(f"cameras must be one of {RAW_CAMERAS}, got {cameras!r}")
    present = [c for c, (a, b, _, _) in _RAW_PAIRS.items()
               if (drive_dir / a).is_dir() and (drive_dir / b).is_dir()]
    if cameras == "auto":
        if not present:
            raise ValueError(f"{drive_dir}: no stereo pair (expected image_02/ and image_03/, or "
                             "image_00/ and image_01/)")
        return present[0]
    if cameras not in present:
        a, b = _RAW_PAIRS[cameras][:2]
        others = f"; it holds the {present[0]} pair" if present else ""
        raise ValueError(f"{drive_dir}: the {cameras} pair ({a}/, {b}/) is missing{others}")
    return cameras


def open_raw(
    root: str | Path,
    date: str,
    drive: str | int,
    poses: str | Path | np.ndarray | None = None,
    cameras: str = "auto",
) -> StereoSequence:
    """Open KITTI raw drive ``DATE_drive_NNNN_sync``.

    ``cameras``: ``colour`` (``image_02``/``image_03`` with ``P_rect_02``/``P_rect_03``), ``grey``
    (``image_00``/``image_01`` with ``P_rect_00``/``P_rect_01``) or ``auto`` (the colour pair when the
    drive has it, else the grey one; :func:`raw_cameras`). Grey images are read as 3 equal channels by
    :func:`load_image`, so every consumer of colour images takes them unchanged.
    ``poses``: ground truth as an array ``[N, 4, 4]``, or a pose file (KITTI or TUM text, or the
    ``.mat`` layout whose ``poses_gt`` is used), or None. Times come from the left camera's
    ``timestamps.txt`` in seconds since the first frame.
    """
    root = Path(root)
    problem = _name_problem(str(date), "date", root, "2011_09_26")
    if problem is not None:
        raise ValueError(problem)
    if not str(drive).isdigit():
        raise ValueError(f"drive {drive!r}: expected a drive number such as 0001 (DATE_drive_NNNN_sync)")
    drive_name = f"{date}_drive_{int(drive):04d}"
    drive_dir = root / date / f"{drive_name}_sync"
    if not drive_dir.is_dir():
        raise FileNotFoundError(f"{drive_dir}: raw drive folder not found")
    left_dir, right_dir, left_key, right_key = _RAW_PAIRS[raw_cameras(drive_dir, cameras)]
    left, right = _pair_files(drive_dir / left_dir / "data", drive_dir / right_dir / "data")
    calib_path = root / date / "calib_cam_to_cam.txt"
    image_size = _image_size(left[0])
    K, baseline = stereo_calibration(calib_path, left_key, right_key, image_size)
    times_path = drive_dir / left_dir / "timestamps.txt"
    times = _read_timestamps(times_path, len(left))
    sources = [calib_path, times_path]
    gt = None
    if poses is not None:
        if isinstance(poses, np.ndarray):
            label = f"{drive_name} ground truth"
            gt = _check_poses(validate_poses(poses, label), len(left), label)
        else:
            gt = _check_poses(read_ground_truth(poses), len(left), str(poses))
            sources.append(Path(poses))
    return StereoSequence(
        name=drive_name, images=ImageFiles(left, right), K=K, baseline=baseline,
        image_size=image_size, times=times, poses=gt, sources=tuple(sources),
    )
