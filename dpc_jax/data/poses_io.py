"""Trajectory files: readers, writers and the check of poses read from files (``validate_poses``).

A trajectory is a numpy array ``[N, 4, 4]`` of camera-to-world poses ``T_w_c`` ("Twv", docs/method.md §1).
Readers return float64 poses whose rotations are projected onto SO(3); they reject malformed
rows, non-finite values and far-from-rigid matrices with a ``ValueError`` naming the file and the
line (text formats) or the key (``.mat``). Writers are atomic: the text goes to a temporary file in
the target directory, which then replaces the target, so a crash never leaves a half-written file.
Pose algebra (relative poses, composition, static frames) is :mod:`dpc_jax.geometry.poses`.

Formats:

* **KITTI** pose text: one pose per line, the 12 numbers of the 3×4 matrix ``[R | t]`` row-major.
* **TUM** text: ``timestamp tx ty tz qx qy qz qw`` per line (Hamilton quaternion, scalar last);
  lines starting with ``#`` are comments. Timestamps must increase from line to line. Two
  trajectories that both have times are paired by time (:func:`associate`, evo's rule; ``dpc-jax
  evaluate`` does this); one paired with frames or with a trajectory without times is paired by
  order, so there a step more than ``TUM_GAP_FACTOR`` times the median step (a stretch of missing
  poses) is reported with an :class:`~dpc_jax._io.InputWarning` naming the line
  (:func:`read_trajectory`, :func:`read_tum`); the file is still read (the evaluation exports of
  static-frame-free sequences have such steps on purpose).
* **.mat** (ss-DPC-Net / pyslam release): ``poses_gt`` and ``poses_est`` as ``4 × 4 × N`` arrays
  and ``convention`` ``'Twv'`` (camera-to-world) or ``'Tvw'`` (world-to-camera, inverted on read).
  A file without ``convention`` is read as ``'Twv'``, the convention of every published file, and
  an :class:`~dpc_jax._io.InputWarning` says so. :func:`read_trajectory` returns the estimate unless
  asked for ``poses_gt``.

Writers refuse an empty path (which would be the current folder) with a ``ValueError``.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from dpc_jax._io import EMPTY_PATH, InputWarning, atomic_write

# validate_poses lives with the pose algebra (pure numpy) so that the API functions of
# dpc_jax.geometry check their poses as the readers do; re-exported here, where it began.
from dpc_jax.geometry.poses import invert_poses, validate_poses

FORMATS = ("kitti", "tum", "mat")
WRITE_FORMATS = ("kitti", "tum")
MAT_KEYS = ("poses_gt", "poses_est")
TUM_GAP_FACTOR = 10.0
# The largest time difference (s) of two poses paired by :func:`associate`: evo's default (--t_max_diff).
MAX_TIME_DIFF = 0.01


# ----------------------------------------------------------------------------- text parsing


def _data_lines(path: Path, comment: str | None) -> list[tuple[int, list[str]]]:
    """``(line number, fields)`` of every non-blank, non-comment line of a text file."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise ValueError(f"{path}: not a text file ({error})") from None
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or (comment is not None and stripped.startswith(comment)):
            continue
        rows.append((number, stripped.replace(",", " ").split()))
    if not rows:
        raise ValueError(f"{path}: no poses (the file is empty)")
    return rows


def _parse_rows(
    path: Path, rows: list[tuple[int, list[str]]], width: int, what: str
) -> tuple[np.ndarray, list[int]]:
    """Parse rows of exactly ``width`` finite numbers into ``[N, width]`` float64 plus line numbers."""
    values = np.empty((len(rows), width))
    for k, (number, fields) in enumerate(rows):
        if len(fields) != width:
            raise ValueError(
                f"{path}, line {number}: expected {width} numbers ({what}), got {len(fields)}"
            )
        try:
            values[k] = [float(f) for f in fields]
        except ValueError:
            raise ValueError(f"{path}, line {number}: not a number in {' '.join(fields)!r}") from None
        if not np.isfinite(values[k]).all():
            raise ValueError(f"{path}, line {number}: non-finite value (NaN or inf)")
    return values, [number for number, _ in rows]


def _validate_lines(poses: np.ndarray, path: Path, lines: list[int]) -> np.ndarray:
    """:func:`validate_poses` with the failing pose mapped to its line in ``path``."""
    try:
        return validate_poses(poses, source=str(path))
    except ValueError as error:
        for i in range(poses.shape[0]):
            try:
                validate_poses(poses[i : i + 1], source=str(path))
            except ValueError:
                raise ValueError(f"{error} (line {lines[i]})") from None
        raise


# ----------------------------------------------------------------------------- quaternions


def _quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Unit quaternions ``[N, 4]`` as ``(x, y, z, w)`` -> rotation matrices ``[N, 3, 3]``."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _rotation_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[N, 3, 3]`` -> unit quaternions ``[N, 4]`` ``(x, y, z, w)`` with ``w ≥ 0``.

    Shepperd's method: the largest of ``4w², 4x², 4y², 4z²`` is computed from the diagonal and the
    others from off-diagonal sums, which keeps every branch well conditioned.
    """
    r = rotation
    trace = r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]
    candidates = np.stack([trace, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], -1)
    branch = np.argmax(candidates, axis=-1)
    q = np.empty((r.shape[0], 4))
    for b in range(4):
        sel = branch == b
        m = r[sel]
        if b == 0:
            s = 2.0 * np.sqrt(1.0 + trace[sel])
            q[sel] = np.stack(
                [(m[:, 2, 1] - m[:, 1, 2]) / s, (m[:, 0, 2] - m[:, 2, 0]) / s,
                 (m[:, 1, 0] - m[:, 0, 1]) / s, 0.25 * s], -1)
        elif b == 1:
            s = 2.0 * np.sqrt(1.0 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2])
            q[sel] = np.stack(
                [0.25 * s, (m[:, 0, 1] + m[:, 1, 0]) / s, (m[:, 0, 2] + m[:, 2, 0]) / s,
                 (m[:, 2, 1] - m[:, 1, 2]) / s], -1)
        elif b == 2:
            s = 2.0 * np.sqrt(1.0 + m[:, 1, 1] - m[:, 0, 0] - m[:, 2, 2])
            q[sel] = np.stack(
                [(m[:, 0, 1] + m[:, 1, 0]) / s, 0.25 * s, (m[:, 1, 2] + m[:, 2, 1]) / s,
                 (m[:, 0, 2] - m[:, 2, 0]) / s], -1)
        else:
            s = 2.0 * np.sqrt(1.0 + m[:, 2, 2] - m[:, 0, 0] - m[:, 1, 1])
            q[sel] = np.stack(
                [(m[:, 0, 2] + m[:, 2, 0]) / s, (m[:, 1, 2] + m[:, 2, 1]) / s, 0.25 * s,
                 (m[:, 1, 0] - m[:, 0, 1]) / s], -1)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[:, 3:4] < 0.0, -q, q)


# ----------------------------------------------------------------------------- readers


def read_kitti_poses(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a KITTI pose file -> ``[N, 4, 4]`` float64 (rotations projected onto SO(3))."""
    path = Path(path)
    values, lines = _parse_rows(path, _data_lines(path, comment=None), 12, "a row-major 3×4 pose")
    return _validate_lines(values.reshape(-1, 3, 4), path, lines)


def read_tum(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory -> ``(timestamps [N] float64, poses [N, 4, 4] float64)``.

    Quaternions must have unit norm within 1e-3 (rounding in text files); they are normalised.
    Timestamps must increase; a step over ``TUM_GAP_FACTOR`` × the median step warns (see the
    module docstring).
    """
    return _read_tum(Path(path), warn_gaps=True)


def _read_tum(path: Path, warn_gaps: bool) -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_tum`; ``warn_gaps``: warn about a jump in the times (poses paired by order)."""
    values, lines = _parse_rows(
        path, _data_lines(path, comment="#"), 8, "timestamp tx ty tz qx qy qz qw"
    )
    _check_timestamps(path, values[:, 0], lines, warn_gaps)
    q = values[:, 4:8]
    norm = np.linalg.norm(q, axis=-1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-3)
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"{path}, line {lines[i]}: quaternion (qx qy qz qw) has norm {norm[i]:.6g}, expected 1"
        )
    poses = np.zeros((values.shape[0], 4, 4))
    poses[:, :3, :3] = _quaternion_to_rotation(q / norm[:, None])
    poses[:, :3, 3] = values[:, 1:4]
    poses[:, 3, 3] = 1.0
    return values[:, 0], _validate_lines(poses, path, lines)


def _check_timestamps(path: Path, stamps: np.ndarray, lines: list[int], warn_gaps: bool) -> None:
    """Refuse timestamps that do not increase; with ``warn_gaps``, warn about a step far above the
    median step."""
    steps = np.diff(stamps)
    back = np.flatnonzero(steps <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise ValueError(
            f"{path}, line {lines[i]}: timestamp {stamps[i]:.15g} does not increase "
            f"(line {lines[i - 1]} has {stamps[i - 1]:.15g}); expected one pose per time, in time order"
        )
    if not warn_gaps or steps.size < 2:
        return
    median = float(np.median(steps))
    jumps = np.flatnonzero(steps > TUM_GAP_FACTOR * median)
    if jumps.size:
        i = int(jumps[0]) + 1
        more = f" ({jumps.size} such steps)" if jumps.size > 1 else ""
        warnings.warn(
            f"{path}, line {lines[i]}: timestamps jump by {steps[i - 1]:.6g} s, {steps[i - 1] / median:.0f}× "
            f"the median step of {median:.6g} s{more}; poses are paired by their order, not by time, "
            "so check that the other trajectory skips the same frames",
            InputWarning,
            stacklevel=4,
        )


def associate(
    reference_times: np.ndarray, times: np.ndarray, max_diff: float = MAX_TIME_DIFF, offset: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Pair two trajectories by their times as evo does (``evo.core.sync.associate_trajectories``):
    ``(reference indices [M], indices [M])``, both int64 and increasing.

    ``reference_times`` ``[N]`` and ``times`` ``[K]`` in seconds, each increasing; ``offset`` (s) is
    added to ``times`` (evo's ``--t_offset``). Each time of the shorter of the two is paired with the
    nearest time of the longer one where they differ by at most ``max_diff`` (s); poses without a
    partner within it are left out. Where two poses of the shorter one have the same nearest partner
    (poses closer together than ``2 · max_diff``) evo keeps both pairs; here only the first, so that no
    pose is evaluated twice.
    """
    reference = np.asarray(reference_times, np.float64)
    other = np.asarray(times, np.float64) + float(offset)
    if reference.ndim != 1 or other.ndim != 1:
        raise ValueError(f"times must be 1-D, got shapes {reference.shape} and {other.shape}")
    if not (np.isfinite(max_diff) and max_diff >= 0.0) or not np.isfinite(offset):
        raise ValueError(f"max_diff must be a finite time >= 0 and offset finite, got {max_diff!r}, "
                         f"{offset!r}")
    other_longer = other.size > reference.size
    short, long = (reference, other) if other_longer else (other, reference)
    if short.size == 0 or long.size == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    # The nearest time of the increasing ``long`` to each time of ``short``: one of its two neighbours
    # at the insertion point (evo's argmin over every time, in O(N log N)).
    right = np.minimum(np.searchsorted(long, short), long.size - 1)
    left = np.maximum(right - 1, 0)
    nearest = np.where(np.abs(long[left] - short) <= np.abs(long[right] - short), left, right)
    keep = np.abs(long[nearest] - short) <= max_diff
    short_idx, long_idx = np.flatnonzero(keep), nearest[keep]
    first = np.concatenate([[True], np.diff(long_idx) > 0]) if long_idx.size else np.empty(0, bool)
    short_idx, long_idx = short_idx[first].astype(np.int64), long_idx[first].astype(np.int64)
    return (short_idx, long_idx) if other_longer else (long_idx, short_idx)


def _load_mat(path: Path) -> dict[str, object]:
    import scipy.io

    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        return scipy.io.loadmat(str(path))
    # scipy's parser raises whatever the damaged bytes lead it to (IndexError, struct.error,
    # zlib.error, ...); any failure here means the file is not a readable .mat.
    except Exception as error:
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise ValueError(f"{path}: not a readable MATLAB .mat file ({reason})") from None


def _mat_convention(path: Path, contents: dict[str, object]) -> str:
    """The file's ``convention`` (``'Twv'`` or ``'Tvw'``); ``'Twv'`` with a warning when it has none.
    Asked once the poses are read, so that a file without them is not first warned about."""
    if "convention" not in contents:
        warnings.warn(f"{path}: no 'convention' key; read as 'Twv' (camera-to-world poses, the convention of "
                      "every published file); a file of world-to-camera poses needs convention = 'Tvw'",
                      InputWarning, stacklevel=4)
        return "Twv"
    convention = str(np.asarray(contents["convention"]).ravel()[0]).strip()
    if convention not in ("Twv", "Tvw"):
        raise ValueError(f"{path}: 'convention' must be 'Twv' or 'Tvw', got {convention!r}")
    return convention


def _mat_poses(path: Path, contents: dict[str, object], key: str) -> np.ndarray:
    """The poses stored under ``key``, checked (:func:`_camera_to_world` makes them camera-to-world)."""
    if key not in contents:
        present = sorted(k for k in contents if not k.startswith("__"))
        raise ValueError(f"{path}: no key {key!r} (expected 'poses_gt' and 'poses_est'; found {present})")
    raw = np.asarray(contents[key])
    if raw.ndim != 3 or raw.shape[:2] != (4, 4) or not np.issubdtype(raw.dtype, np.number):
        raise ValueError(f"{path}: {key!r} must be a numeric 4 × 4 × N array, got shape {raw.shape}")
    return validate_poses(np.moveaxis(raw, -1, 0), source=f"{path} [{key!r}]")


def _camera_to_world(path: Path, contents: dict[str, object], *poses: np.ndarray) -> list[np.ndarray]:
    """``poses`` of the file as camera-to-world: inverted when its ``convention`` is ``'Tvw'``."""
    inverted = _mat_convention(path, contents) == "Tvw"
    return [invert_poses(p) if inverted else p for p in poses]


def read_mat(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read an ss-DPC-Net ``.mat`` -> ``(ground truth, estimate)``, each ``[N, 4, 4]`` camera-to-world."""
    path = Path(path)
    contents = _load_mat(path)
    gt = _mat_poses(path, contents, "poses_gt")
    est = _mat_poses(path, contents, "poses_est")
    if gt.shape[0] != est.shape[0]:
        raise ValueError(
            f"{path}: 'poses_gt' has {gt.shape[0]} poses but 'poses_est' has {est.shape[0]}"
        )
    gt, est = _camera_to_world(path, contents, gt, est)
    return gt, est


def detect_format(path: str | os.PathLike[str]) -> str:
    """``"mat"`` for ``.mat``, ``"tum"`` for ``.tum``; other text by its column count (12 KITTI, 8 TUM)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".mat":
        return "mat"
    if suffix == ".tum":
        return "tum"
    number, fields = _data_lines(path, comment="#")[0]
    if len(fields) == 12:
        return "kitti"
    if len(fields) == 8:
        return "tum"
    raise ValueError(
        f"{path}, line {number}: {len(fields)} columns; expected a trajectory of 12 (KITTI: the 3×4 pose "
        "row-major) or 8 (TUM: time tx ty tz qx qy qz qw) numbers per line, or a .mat file"
    )


def read_trajectory(
    path: str | os.PathLike[str], format: str | None = None, mat_key: str = "poses_est"
) -> np.ndarray:
    """Read a trajectory file -> ``[N, 4, 4]`` float64 camera-to-world poses, to be paired by order.

    ``format``: ``"kitti" | "tum" | "mat" | None`` (None: :func:`detect_format`). For ``.mat`` the
    poses under ``mat_key`` are returned: the estimate (``poses_est``, default) or the ground truth
    (``poses_gt``); use :func:`read_mat` for both trajectories. A jump in a TUM file's times warns
    (the module docstring); :func:`read_timed_trajectory` keeps the times instead.
    """
    return _read(Path(path), format, mat_key, warn_gaps=True)[1]


def read_timed_trajectory(
    path: str | os.PathLike[str], format: str | None = None, mat_key: str = "poses_est"
) -> tuple[np.ndarray | None, np.ndarray]:
    """Read a trajectory file with its times -> ``(times [N] s float64, or None for a format without
    times (KITTI, .mat), poses [N, 4, 4] float64)``, for pairing by time (:func:`associate`).
    ``format`` and ``mat_key`` as for :func:`read_trajectory`."""
    return _read(Path(path), format, mat_key, warn_gaps=False)


def _read(
    path: Path, format: str | None, mat_key: str, warn_gaps: bool
) -> tuple[np.ndarray | None, np.ndarray]:
    if mat_key not in MAT_KEYS:
        raise ValueError(f"mat_key must be one of {', '.join(MAT_KEYS)}, got {mat_key!r}")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    fmt = detect_format(path) if format is None else format
    if fmt == "kitti":
        return None, read_kitti_poses(path)
    if fmt == "tum":
        return _read_tum(path, warn_gaps)
    if fmt == "mat":
        contents = _load_mat(path)
        return None, _camera_to_world(path, contents, _mat_poses(path, contents, mat_key))[0]
    raise ValueError(f"{path}: unknown trajectory format {fmt!r}; expected one of {', '.join(FORMATS)}")


# ----------------------------------------------------------------------------- writers


def _check_writable(path: str | os.PathLike[str], poses: np.ndarray) -> np.ndarray:
    """``poses`` as float64, refused (``ValueError`` naming ``poses``) where a reader would refuse the
    file: a writer never makes a trajectory that cannot be read back. Written as given, unprojected.
    An empty ``path`` is refused too: ``Path("")`` is the current folder."""
    if not os.fspath(path):
        raise ValueError(f"path: {EMPTY_PATH}")
    arr = np.asarray(poses, dtype=np.float64)
    validate_poses(arr, source="poses")
    return arr


def kitti_line(pose: np.ndarray) -> str:
    """One pose ``[4, 4]`` (or ``[3, 4]``) as a line of KITTI text: its top 3×4 block, row by row, to full
    float64 precision (the live outputs write a trajectory a line at a time)."""
    return " ".join(f"{v:.17g}" for v in np.asarray(pose, np.float64)[:3].ravel()) + "\n"


def write_kitti_poses(path: str | os.PathLike[str], poses: np.ndarray) -> None:
    """Write ``[N, 4, 4]`` (or ``[N, 3, 4]``) poses as KITTI text (:func:`kitti_line`), atomically."""
    atomic_write(path, "".join(map(kitti_line, _check_writable(path, poses))))


def write_tum(
    path: str | os.PathLike[str], poses: np.ndarray, timestamps: np.ndarray | None = None
) -> None:
    """Write poses as TUM text, atomically. ``timestamps`` ``[N]`` s (default: the frame index)."""
    arr = _check_writable(path, poses)
    n = arr.shape[0]
    stamps = np.arange(n, dtype=np.float64) if timestamps is None else np.asarray(timestamps, np.float64)
    if stamps.shape != (n,) or not np.isfinite(stamps).all():
        raise ValueError(f"timestamps must be {n} finite numbers, got shape {stamps.shape}")
    back = np.flatnonzero(np.diff(stamps) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise ValueError(
            f"timestamps: {stamps[i]:.15g} (pose {i}) does not increase after {stamps[i - 1]:.15g} "
            f"(pose {i - 1}); read_tum refuses such a file, so the times must increase"
        )
    q = _rotation_to_quaternion(validate_poses(arr, source="poses to write")[:, :3, :3])
    rows = np.concatenate([stamps[:, None], arr[:, :3, 3], q], axis=1)
    atomic_write(path, "".join(" ".join(f"{v:.17g}" for v in row) + "\n" for row in rows))


def frames_path(path: str | os.PathLike[str]) -> Path:
    """Where ``dpc_jax.correction.corrector.write_trajectory`` lists a trajectory's source frame numbers:
    ``corrected.txt`` → ``corrected.frames.txt``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.frames.txt")
