"""A ROS recording as a source (``dpc_jax.sources.bag``): recordings written by ``rosbags``' own writers
(tests/recordings.py) from a KITTI odometry sequence give the frames, calibration, times and poses the KITTI
layout gives and the same cache byte for byte; the real drive 0001 as every kind of recording, with raw and
PNG-compressed images, gives `dpc-jax vo` the very trajectory of the raw layout; images of every encoding
decode as OpenCV decodes them; stamps pair left and right; CameraInfo with distortion is rectified as
OpenCV's ``undistort`` does; ``/tf_static`` moves a pose onto the camera; and each bad recording is one
line."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import cv2
import numpy as np
import pytest
from recordings import CAMERA_FRAME, EPOCH_NS, KINDS, Bag, stamps_of, write_raw_recording, write_recording
from support import in_one_process, write_odometry

from dpc_jax.cli import main
from dpc_jax.data.frames import png_grey
from dpc_jax.data.kitti import open_odometry, read_ground_truth
from dpc_jax.sources import BagOptions
from dpc_jax.sources.bag import open_bag
from dpc_jax.sources.bag_reader import BagError

SUFFIX = {"ros1": ".bag", "mcap": ".mcap", "sqlite3": "", "mcap-folder": ""}


@pytest.fixture(scope="module")
def kitti(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A 6-frame odometry sequence of random 48×72 images."""
    tmp = tmp_path_factory.mktemp("recordings")
    written = write_odometry(tmp / "random", "00", n=6, size=(48, 72))
    return {"tmp": tmp, "random": tmp / "random", "poses": written["poses"]}


@pytest.mark.parametrize("compressed", [False, True], ids=["rgb8", "png"])
@pytest.mark.parametrize("kind", KINDS)
def test_every_storage_gives_the_frames_of_the_kitti_layout(kitti: dict, kind: str, compressed: bool) -> None:
    path = write_recording(kitti["tmp"] / f"{kind}-{compressed}{SUFFIX[kind]}", kitti["random"], kind=kind,
                           compressed=compressed, poses={"/odom": kitti["poses"]})
    recording = open_bag(BagOptions(path, prior_topic="/odom", gt_topic="/odom"))
    bag, files = recording.sequence, open_odometry(kitti["random"], "00")
    np.testing.assert_array_equal(bag.K, files.K)
    assert bag.baseline == files.baseline and bag.image_size == files.image_size
    np.testing.assert_array_equal(bag.times, files.times)  # stamps since the first, as times.txt holds them
    assert recording.first_stamp == EPOCH_NS and recording.camera_frame == CAMERA_FRAME
    assert recording.world_frame == "odom" and recording.notes == ()
    pairs = zip(bag.images.stream(bag.image_size), files.images.stream(files.image_size), strict=True)
    for ours, theirs in pairs:
        for grey in (False, True):
            for a, b in zip(ours.decode(grey), theirs.decode(grey), strict=True):
                np.testing.assert_array_equal(a, b)
    # Poses through quaternions: equal to rounding.
    np.testing.assert_allclose(recording.prior, kitti["poses"], atol=1e-12)
    np.testing.assert_allclose(bag.poses, kitti["poses"], atol=1e-12)


def test_poses_of_a_body_frame_named_as_the_camera_are_noted(kitti: dict, tmp_path: Path) -> None:
    """The prior of a body frame (x forward, as ROS's base_link) given as the camera's optical frame (z
    forward): its steps point along x, and a note asks whether the frame is the optical one."""
    body = np.eye(4)
    body[:3, :3] = [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]  # columns: body x, y, z
    assert np.abs(np.diff(kitti["poses"][:, 2, 3])).sum() > 0  # the camera moves along its z
    path = write_recording(tmp_path / "body.mcap", kitti["random"], poses={"/odom": kitti["poses"] @ body})
    notes = open_bag(BagOptions(path, prior_topic="/odom")).notes
    assert any("--prior-topic /odom: its steps point along the camera's x axis" in n for n in notes), notes


def test_the_ground_truth_of_a_pose_topic_is_part_of_the_frames_identity(kitti: dict, tmp_path: Path) -> None:
    """A cache of a recording is identified by the ground truth read from its topic (held in memory, in no
    file the cache hashes): another --gt-topic of the same recording is another cache's input."""
    moved = kitti["poses"].copy()
    moved[:, 0, 3] += 1.0
    path = write_recording(tmp_path / "two_gt.mcap", kitti["random"], poses={"/gt_a": kitti["poses"],
                                                                             "/gt_b": moved})
    identities = [open_bag(BagOptions(path, gt_topic=topic)).sequence.images.identity()
                  for topic in (None, "/gt_a", "/gt_b", "/gt_a")]
    assert identities[0][-1] == "ground truth none"
    assert len({tuple(i) for i in identities}) == 3 and identities[1] == identities[3]


def test_grey_is_what_opencv_decodes_from_a_colour_png() -> None:
    rgb = np.random.default_rng(1).integers(0, 256, (64, 96, 3), dtype=np.uint8)
    ok, png = cv2.imencode(".png", rgb[..., ::-1])
    assert ok
    np.testing.assert_array_equal(png_grey(rgb), cv2.imdecode(png, cv2.IMREAD_GRAYSCALE))


def _one_camera_pair(tmp: Path, name: str, kind: str, write_frame, n: int = 3) -> Path:
    """A recording of ``n`` frames whose image messages ``write_frame(bag, k, stamp)`` writes, with the
    CameraInfo of a 20×32 rectified pair."""
    bag = Bag(tmp / f"{name}{SUFFIX[kind]}", kind)
    P = np.array([[30.0, 0, 15.5, 0], [0, 30.0, 9.5, 0], [0, 0, 1, 0]])
    Pr = P.copy()
    Pr[0, 3] = -30.0 * 0.5
    for k, stamp in enumerate(stamps_of(np.arange(n) * 0.1)):
        for topic, matrix in (("/left/camera_info", P), ("/right/camera_info", Pr)):
            bag.write(topic, stamp, bag.camera_info(stamp, "cam", (20, 32), matrix))
        write_frame(bag, k, stamp)
    return bag.close()


def test_encodings_decode_as_opencv_does(tmp_path: Path) -> None:
    """mono8 (and 8UC1), bgr8, mono16 (little and big endian, scaled by its high byte as OpenCV reads a
    16-bit PNG) and JPEG: the decoded images against OpenCV's decoding of the same pixels from files."""
    rng = np.random.default_rng(2)
    colour = rng.integers(0, 256, (3, 20, 32, 3), dtype=np.uint8)
    deep = rng.integers(0, 65536, (3, 20, 32), dtype=np.uint16)
    jpegs = [cv2.imencode(".jpg", c)[1].tobytes() for c in colour]
    cases = {
        "mono8": lambda bag, k, s, topic: bag.image(s, "cam", colour[k, ..., 0], "mono8"),
        "8UC1": lambda bag, k, s, topic: bag.image(s, "cam", colour[k, ..., 0], "8UC1"),
        "bgr8": lambda bag, k, s, topic: bag.image(s, "cam", colour[k], "bgr8"),
        "mono16": lambda bag, k, s, topic: bag.image(s, "cam", deep[k], "mono16"),
        "mono16be": lambda bag, k, s, topic: _big_endian(bag.image(s, "cam", deep[k].byteswap(), "mono16")),
        "jpeg": lambda bag, k, s, topic: bag.compressed(s, "cam", jpegs[k], "jpeg"),
    }
    for name, message in cases.items():
        def frame(bag: Bag, k: int, stamp: int, message=message) -> None:
            for topic in ("/left/image", "/right/image"):
                bag.write(topic, stamp, message(bag, k, stamp, topic))

        sequence = open_bag(BagOptions(_one_camera_pair(tmp_path, name, "mcap", frame))).sequence
        for k, read in enumerate(sequence.images.stream(sequence.image_size)):
            for grey in (False, True):
                left, right = read.decode(grey)
                np.testing.assert_array_equal(left, right)
                path = tmp_path / f"{name}{k}.png"
                if name in ("mono8", "8UC1"):
                    cv2.imwrite(str(path), colour[k, ..., 0])
                elif name == "bgr8":
                    cv2.imwrite(str(path), colour[k])
                elif name.startswith("mono16"):
                    cv2.imwrite(str(path), deep[k])
                else:
                    path = path.with_suffix(".jpg")
                    path.write_bytes(jpegs[k])
                flag = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR
                reference = cv2.imread(str(path), flag)
                np.testing.assert_array_equal(left, reference if grey else reference[..., ::-1])

    # 12-bit data in the low bits of mono16: read by the high byte, so dark, and a note says so.
    def twelve(bag: Bag, k: int, stamp: int) -> None:
        for topic in ("/left/image", "/right/image"):
            bag.write(topic, stamp, bag.image(stamp, "cam", deep[k] >> 4, "mono16"))

    opened = open_bag(BagOptions(_one_camera_pair(tmp_path, "twelve", "mcap", twelve)))
    assert any("/left/image: the mono16 values of its first image use 12 bits" in n for n in opened.notes)
    assert not any("mono16" in n for n in open_bag(BagOptions(tmp_path / "mono16.mcap")).notes)


def _big_endian(message):
    message.is_bigendian = 1
    return message


def test_left_and_right_pair_by_stamp_and_the_unpaired_are_counted(tmp_path: Path) -> None:
    """Right stamps 2 ms late with jitter, one right image missing (frame 2), one right image alone between
    frames: each left image takes its nearest right within the tolerance; the rest are skipped and counted."""
    images = np.random.default_rng(3).integers(0, 256, (6, 20, 32, 3), dtype=np.uint8)
    late = [2_000_000, 1_500_000, None, 2_500_000, 1_000_000, 2_000_000]

    def frame(bag: Bag, k: int, stamp: int) -> None:
        bag.write("/left/image", stamp, bag.image(stamp, "cam", images[k], "rgb8"))
        if late[k] is not None:
            bag.write("/right/image", stamp + late[k], bag.image(stamp + late[k], "cam", images[k], "rgb8"))
        if k == 3:
            alone = stamp + 50_000_000  # 50 ms after frame 3: within no frame's tolerance
            bag.write("/right/image", alone, bag.image(alone, "cam", images[0], "rgb8"))

    path = _one_camera_pair(tmp_path, "pairs", "ros1", frame, n=6)
    recording = open_bag(BagOptions(path))
    assert recording.notes == (f"{path}: 1 left and 1 right images without a partner within 10 ms skipped (5 "
                               "stereo frames)",)
    sequence = recording.sequence
    np.testing.assert_allclose(sequence.times, [0.0, 0.1, 0.3, 0.4, 0.5])
    for k, read in zip((0, 1, 3, 4, 5), sequence.images.stream(sequence.image_size), strict=True):
        left, right = read.decode()
        np.testing.assert_array_equal(left, images[k])
        np.testing.assert_array_equal(right, images[k])
    tight = open_bag(BagOptions(path, tolerance=0.0018))  # frames 0, 3 and 5 are 2 ms or more apart
    assert len(tight.sequence) == 2


def test_a_repeated_stamp_keeps_the_first_image_and_a_stamp_going_back_is_refused(tmp_path: Path) -> None:
    """Frame 1's left image published twice (a second, different image under the same stamp) and frame 3's
    right image too: each second image is dropped with a note, every frame pairs the first images; an image
    stamped before the one it follows stops the reading with one line naming it."""
    images = np.random.default_rng(4).integers(0, 256, (5, 20, 32, 3), dtype=np.uint8)

    def frame(bag: Bag, k: int, stamp: int) -> None:
        for topic in ("/left/image", "/right/image"):
            bag.write(topic, stamp, bag.image(stamp, "cam", images[k], "rgb8"))
            if (topic, k) in (("/left/image", 1), ("/right/image", 3)):
                bag.write(topic, stamp, bag.image(stamp, "cam", 255 - images[k], "rgb8"))

    path = _one_camera_pair(tmp_path, "repeats", "mcap", frame, n=5)
    recording = open_bag(BagOptions(path))
    assert recording.notes == tuple(
        f"{path}: {topic}: 1 image(s) repeat the header stamp of the image before them (the first: image "
        f"{number} at {at / 1e9:.9f} s); the first image of each stamp is kept"
        for topic, number, at in zip(("/left/image", "/right/image"), (2, 4), stamps_of([0.1, 0.3]),
                                     strict=True))
    sequence = recording.sequence
    np.testing.assert_allclose(sequence.times, np.arange(5) * 0.1)
    for k, read in enumerate(sequence.images.stream(sequence.image_size)):
        left, right = read.decode()
        np.testing.assert_array_equal(left, images[k])
        np.testing.assert_array_equal(right, images[k])

    def back(bag: Bag, k: int, stamp: int) -> None:
        for topic in ("/left/image", "/right/image"):
            at = stamp - 150_000_000 if (topic, k) == ("/left/image", 2) else stamp  # before frame 1's
            bag.write(topic, stamp, bag.image(at, "cam", images[k], "rgb8"))

    path = _one_camera_pair(tmp_path, "back", "mcap", back, n=3)
    with pytest.raises(BagError) as refused:
        open_bag(BagOptions(path))
    early, first = (at / 1e9 for at in stamps_of([0.05, 0.1]))
    assert str(refused.value) == (f"{path}: /left/image: the header stamp of image 2 ({early:.9f} s) goes "
                                  f"back from image 1's ({first:.9f} s); expected increasing stamps")


def test_distorted_cameras_are_rectified_as_opencv_undistorts(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    image = cv2.GaussianBlur(rng.integers(0, 256, (40, 64, 3), dtype=np.uint8), (5, 5), 2)
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 19.5], [0, 0, 1]])
    D = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])
    P = np.array([[45.0, 0, 32.0, 0], [0, 45.0, 20.0, 0], [0, 0, 1, 0]])
    Pr = P.copy()
    Pr[0, 3] = -45.0 * 0.3
    bag = Bag(tmp_path / "distorted.mcap", "mcap")
    for stamp in stamps_of([0.0, 0.1]):
        for side, matrix in (("left", P), ("right", Pr)):
            info = bag.camera_info(stamp, "cam", (40, 64), matrix, D=D, K=K)
            bag.write(f"/{side}/camera_info", stamp, info)
            bag.write(f"/{side}/image", stamp, bag.image(stamp, "cam", image, "rgb8"))
    sequence = open_bag(BagOptions(bag.close())).sequence
    np.testing.assert_array_equal(sequence.K, P[:, :3])
    assert sequence.baseline == pytest.approx(0.3)
    left, _ = next(iter(sequence.images.stream(sequence.image_size))).decode()
    reference = cv2.undistort(image, K, D, None, P[:, :3])
    # The remapping is part of the inputs a cache of these frames is identified by.
    remap = [line for line in sequence.images.identity() if line.startswith("remap ")]
    assert len(remap) == 1 and remap != ["remap none"]
    inside = (slice(4, -4), slice(4, -4))  # the border: how each fills pixels mapped from outside
    assert np.abs(left[inside].astype(int) - reference[inside]).max() <= 1


def test_an_image_rect_topic_is_not_rectified_again_and_a_bad_d_is_one_line(tmp_path: Path) -> None:
    """``image_proc``'s ``image_rect`` beside the raw camera's CameraInfo (distortion, R): the images are used
    as they are, with P, and a note says so; a raw camera's D of a length OpenCV has no model for is refused
    in one line naming the topic."""
    rng = np.random.default_rng(5)
    image = cv2.GaussianBlur(rng.integers(0, 256, (40, 64, 3), dtype=np.uint8), (5, 5), 2)
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 19.5], [0, 0, 1]])
    P = np.array([[45.0, 0, 32.0, 0], [0, 45.0, 20.0, 0], [0, 0, 1, 0]])
    Pr = P.copy()
    Pr[0, 3] = -45.0 * 0.3
    R = cv2.Rodrigues(np.array([0.0, 0.01, 0.0]))[0]

    def write(name: str, D: np.ndarray, image_name: str) -> Path:
        bag = Bag(tmp_path / name, "mcap")
        for stamp in stamps_of([0.0, 0.1]):
            for side, matrix in (("left", P), ("right", Pr)):
                bag.write(f"/{side}/camera_info", stamp, bag.camera_info(stamp, "cam", (40, 64), matrix, D=D,
                                                                         K=K, R=R))
                bag.write(f"/{side}/{image_name}", stamp, bag.image(stamp, "cam", image, "rgb8"))
        return bag.close()

    D = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])
    opened = open_bag(BagOptions(write("rect.mcap", D, "image_rect")))
    left, _ = next(iter(opened.sequence.images.stream(opened.sequence.image_size))).decode()
    np.testing.assert_array_equal(left, image)
    np.testing.assert_array_equal(opened.sequence.K, P[:, :3])
    assert any("/left/image_rect is a rectified topic" in note for note in opened.notes)
    assert "remap none" in opened.sequence.images.identity()
    bad = write("bad_d.mcap", D[:3], "image_raw")
    with pytest.raises(ValueError, match=r"bad_d\.mcap: /left/camera_info: D holds 3 coefficients; expected"):
        open_bag(BagOptions(bad))


def test_tf_static_moves_the_prior_onto_the_camera(kitti: dict, tmp_path: Path) -> None:
    """Odometry of base_link, with /tf_static holding base_link → cam_left: the prior is T_world_base ·
    T_base_cam; without the link, one line names both frames and --pose-frame."""
    from scipy.spatial.transform import Rotation

    link = np.eye(4)
    link[:3, :3] = Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix()
    link[:3, 3] = [0.3, 0.0, 1.2]
    poses = kitti["poses"]

    def extra(bag: Bag, k: int, stamp: int) -> None:
        bag.write("/odom", stamp, bag.odometry(stamp, "map", "base_link", poses[k]))
        if k == 0:
            bag.write("/tf_static", stamp, bag.transform(stamp, "base_link", CAMERA_FRAME, link))

    path = write_recording(tmp_path / "tf.mcap", kitti["random"], frames=extra)
    recording = open_bag(BagOptions(path, prior_topic="/odom"))
    np.testing.assert_allclose(recording.prior, poses @ link, atol=1e-12)
    assert recording.world_frame == "map"
    def odometry(bag: Bag, k: int, stamp: int) -> None:
        bag.write("/odom", stamp, bag.odometry(stamp, "map", "base_link", poses[k]))

    unlinked = write_recording(tmp_path / "unlinked.db3", kitti["random"], kind="sqlite3", frames=odometry)
    with pytest.raises(ValueError, match=r"poses of frame 'base_link', images of frame 'cam_left'.*"
                       "--pose-frame cam_left if the two coincide"):
        open_bag(BagOptions(unlinked, prior_topic="/odom"))
    same = open_bag(BagOptions(unlinked, prior_topic="/odom", pose_frame=CAMERA_FRAME))
    np.testing.assert_allclose(same.prior, poses, atol=1e-12)


def test_a_moving_tf_chain_moves_the_prior_onto_the_camera(kitti: dict, tmp_path: Path) -> None:
    """Odometry of base_link; /tf holds base_link → gimbal, turning from frame to frame (stamped 2 ms after
    each frame, within the tolerance), and /tf_static gimbal → cam_left: the prior is T_world_base ·
    T_base_gimbal(frame) · T_gimbal_cam. A frame without a transform of the chain is one line naming it."""
    from scipy.spatial.transform import Rotation

    poses = kitti["poses"]
    mount = np.eye(4)
    mount[:3, :3] = Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix()
    mount[:3, 3] = [0.1, 0.0, 0.05]
    turns = np.tile(np.eye(4), (len(poses), 1, 1))
    for k in range(len(poses)):
        turns[k, :3, :3] = Rotation.from_euler("z", 5.0 * k, degrees=True).as_matrix()
        turns[k, :3, 3] = [0.3, 0.0, 1.2 + 0.01 * k]

    def chain(missing: int | None):
        def extra(bag: Bag, k: int, stamp: int) -> None:
            bag.write("/odom", stamp, bag.odometry(stamp, "map", "base_link", poses[k]))
            if k != missing:
                bag.write("/tf", stamp + 2_000_000, bag.transform(stamp + 2_000_000, "base_link", "gimbal",
                                                                  turns[k]))
            if k == 0:
                bag.write("/tf_static", stamp, bag.transform(stamp, "gimbal", CAMERA_FRAME, mount))
        return extra

    path = write_recording(tmp_path / "moving.mcap", kitti["random"], frames=chain(None))
    prior = open_bag(BagOptions(path, prior_topic="/odom")).prior
    expected = np.stack([poses[k] @ turns[k] @ mount for k in range(len(poses))])
    np.testing.assert_allclose(prior, expected, atol=1e-12)
    gap = write_recording(tmp_path / "gap", kitti["random"], kind="sqlite3", frames=chain(3))
    with pytest.raises(ValueError, match=r"/tf has no transform base_link → gimbal within 10 ms of frame 3"):
        open_bag(BagOptions(gap, prior_topic="/odom"))


@pytest.mark.parametrize("kind,compressed", [("ros1", False), ("mcap", True)])
def test_the_cache_of_a_recording_is_that_of_the_kitti_layout_byte_for_byte(
    kitti: dict, tmp_path: Path, kind: str, compressed: bool
) -> None:
    from dpc_jax.data.cache import prepare_sequence

    root = kitti["random"]
    path = write_recording(tmp_path / f"rec{SUFFIX[kind]}", root, kind=kind, compressed=compressed)
    prior = read_ground_truth(root / "poses" / "00.txt")
    caches = []
    sources = (("files", open_odometry(root, "00")), ("bag", open_bag(BagOptions(path)).sequence))
    for name, sequence in sources:
        caches.append(prepare_sequence(sequence, prior, tmp_path / name, size=(24, 36), flow=True,
                                       ground_truth=prior, name="00", progress=False, workers=2))
    arrays = sorted(p.name for p in caches[0].iterdir() if p.suffix == ".npy")
    assert {"left.npy", "right.npy", "flow.npy", "prior.npy", "times.npy"} <= set(arrays), arrays
    for array in arrays:
        assert (caches[0] / array).read_bytes() == (caches[1] / array).read_bytes(), array


def test_prepare_on_a_ros2_bag_folder_is_prepare_on_the_kitti_layout(kitti: dict, tmp_path: Path) -> None:
    """`dpc-jax prepare --bag` (a ROS 2 bag folder of sqlite3 storage) and `--kitti-odometry` with the same
    prior and ground-truth file (the layout's poses/00.txt): the same arrays; with `--prior-topic`, the same
    prior to rounding."""
    from dpc_jax.data.sequence_cache import load_cache

    root = kitti["random"]
    folder = write_recording(tmp_path / "run", root, kind="sqlite3", poses={"/odom": kitti["poses"]})
    prior = root / "poses" / "00.txt"
    common = ["--out", str(tmp_path / "cache"), "--size", "24x36", "--no-progress"]
    assert main(["prepare", "--kitti-odometry", str(root), "--sequence", "00", "--prior", str(prior),
                 *common]) == 0
    assert main(["prepare", "--bag", str(folder), "--prior", str(prior), "--gt", str(prior), *common]) == 0
    files, bag = tmp_path / "cache" / "00", tmp_path / "cache" / "run"
    arrays = sorted(p.name for p in files.glob("*.npy"))
    assert len(arrays) >= 6 and arrays == sorted(p.name for p in bag.glob("*.npy"))
    for array in arrays:
        assert (files / array).read_bytes() == (bag / array).read_bytes(), array
    assert main(["prepare", "--bag", str(folder), "--prior-topic", "/odom", "--out",
                 str(tmp_path / "topic"), "--size", "24x36", "--no-progress"]) == 0
    from_topic = load_cache(tmp_path / "topic" / "run").prior
    np.testing.assert_allclose(from_topic, load_cache(files).prior, atol=1e-12)


def _median_inliers(printed: str) -> list[int]:
    """The median inliers of each `dpc-jax vo` run's summary line in its printed output."""
    return [int(line.split("median inliers ")[1].split(",")[0])
            for line in printed.splitlines() if "median inliers" in line]


# The frames of the real drive 0001 that `vo --bag` runs on: three pairs, enough for a median of inliers.
DRIVE_FRAMES = 4


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The raw layout of the real drive 0001 and `dpc-jax vo`'s trajectory of its first frames from the
    layout's files, as bytes (once for the module)."""
    from conftest import DATA

    raw, tmp = DATA / "kitti-raw", tmp_path_factory.mktemp("drive")
    out, printed = tmp / "files.txt", io.StringIO()
    with contextlib.redirect_stdout(printed):
        status = main(["vo", "--kitti-raw", str(raw), "--date", "2011_09_26", "--drive", "1", "--frames",
                       f"0:{DRIVE_FRAMES}", "--out", str(out), "--no-progress"])
    assert status == 0, f"dpc-jax vo on {raw}"
    inliers = _median_inliers(printed.getvalue())
    assert len(inliers) == 1 and inliers[0] > 50  # the VO tracked: the equality is not of extrapolations
    return {"raw": raw, "trajectory": out.read_bytes()}


@pytest.mark.parametrize("compressed", [False, True], ids=["raw", "png"])
@pytest.mark.parametrize("kind", KINDS)
def test_vo_on_a_recorded_kitti_drive_is_vo_on_its_files(
    drive: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str, compressed: bool
) -> None:
    """The first frames of the real drive 0001 (colour, 375×1242) as each kind of recording, with raw
    (``rgb8``) or PNG-compressed images: `dpc-jax vo --bag` writes the very trajectory it writes from the
    raw layout's files (stamps from timestamps.txt, P from P_rect)."""
    path = write_raw_recording(tmp_path / f"drive{SUFFIX[kind]}", drive["raw"], "2011_09_26", "0001",
                               DRIVE_FRAMES, kind=kind, compressed=compressed)
    assert main(["vo", "--bag", str(path), "--out", str(tmp_path / "bag.txt"), "--no-progress"]) == 0
    assert (tmp_path / "bag.txt").read_bytes() == drive["trajectory"]
    inliers = _median_inliers(capsys.readouterr().out)
    assert len(inliers) == 1 and inliers[0] > 50


def test_evaluate_reads_trajectories_from_pose_topics_paired_by_stamp(
    kitti: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`evaluate --gt REC:TOPIC --est REC:TOPIC`: the metrics of the same poses as KITTI text files, with the
    estimate's poses stamped 3 ms after the frames (paired by stamp within evo's 10 ms) and one extra pose
    between frames that pairs with none; a ground truth of another frame (``base_link``) warns that the
    topics are compared as recorded."""
    import json

    from dpc_jax.data.poses_io import write_kitti_poses

    gt = kitti["poses"]
    est = gt.copy()
    est[:, :3, 3] += np.random.default_rng(5).normal(0, 0.05, (len(gt), 3))

    def poses(bag: Bag, k: int, stamp: int) -> None:
        bag.write("/gt", stamp, bag.odometry(stamp, "odom", CAMERA_FRAME, gt[k]))
        bag.write("/base", stamp, bag.odometry(stamp, "odom", "base_link", gt[k]))
        bag.write("/est", stamp + 3_000_000, bag.odometry(stamp + 3_000_000, "odom", CAMERA_FRAME, est[k]))
        if k == 2:
            alone = stamp + 50_000_000
            bag.write("/est", alone, bag.odometry(alone, "odom", CAMERA_FRAME, est[k]))

    path = write_recording(tmp_path / "poses.bag", kitti["random"], kind="ros1", frames=poses)
    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "est.txt", est)
    results, errors = [], []
    for pair in ((f"{path}:/gt", f"{path}:/est"), (tmp_path / "gt.txt", tmp_path / "est.txt"),
                 (f"{path}:/base", f"{path}:/est")):
        argv = ["evaluate", "--gt", str(pair[0]), "--est", str(pair[1]), "--label", "est", "--json", "-"]
        assert main(argv) == 0
        out, err = capsys.readouterr()
        results.append(json.loads(out))
        errors.append(err)
    topics, files, base = (result["estimates"]["est"] for result in results)
    assert sum(isinstance(value, float) for value in files.values()) >= 4, files
    for key, value in files.items():
        if isinstance(value, float):
            assert topics[key] == pytest.approx(value, rel=1e-9, abs=1e-12), key
            assert base[key] == topics[key], key
    assert "different frames" not in errors[0] + errors[1]
    assert errors[2].count("\n") == 1 and (f"different frames ({path}:/base of 'base_link', {path}:/est of "
                                            f"'{CAMERA_FRAME}')") in errors[2], errors[2]
    _fails(capsys, ["evaluate", "--gt", f"{path}:/nowhere", "--est", f"{path}:/est"], str(path),
           "/nowhere: no such topic", "its pose topics: /base, /est, /gt")


# --------------------------------------------------------------------------- bad recordings


def _write(tmp: Path, name: str, kind: str = "mcap", **images) -> Path:
    """A 3-frame recording whose messages ``images`` (topic → writer(bag, k, stamp)) make."""
    def frame(bag: Bag, k: int, stamp: int) -> None:
        for topic, write in images.items():
            write(bag, k, stamp, topic)

    return _one_camera_pair(tmp, name, kind, frame)


def _rgb(size=(20, 32)):
    image = np.zeros((*size, 3), np.uint8)
    return lambda bag, k, stamp, topic: bag.write(topic, stamp, bag.image(stamp, "cam", image, "rgb8"))


def _fails(capsys, argv: list[str], *expected: str) -> None:
    assert main(argv) != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for text in expected:
        assert text in err, err


def test_bad_recordings_get_one_line(kitti: dict, tmp_path: Path, capsys) -> None:
    out = tmp_path / "vo.txt"
    vo = ["vo", "--out", str(out), "--no-progress", "--bag"]
    no_images = _write(tmp_path, "no-images")
    _fails(capsys, [*vo, str(no_images)], str(no_images), "no image topic", "/left/camera_info")
    one = _write(tmp_path, "one", **{"/left/image": _rgb()})
    _fails(capsys, [*vo, str(one)], str(one), "one camera only (/left/image)")
    # Before JAX starts: prepare and correct (which start it) read the recording's index first.
    status, imported, done = in_one_process([["prepare", "--bag", one, "--prior-topic", "/odom", "--out",
                                              tmp_path / "cache"]])
    assert status == [1] and imported == [] and "one camera only" in done.stderr
    topics = ("/left/image", "/right/image", "/left/rect", "/right/rect")
    two_pairs = _write(tmp_path, "two-pairs", **{t: _rgb() for t in topics})
    _fails(capsys, [*vo, str(two_pairs)], "2 stereo pairs", "/left/rect", "--left-topic and --right-topic")
    _fails(capsys, [*vo, str(two_pairs), "--left-topic", "/left/image", "--right-topic", "/nowhere"],
           str(two_pairs), "--right-topic /nowhere: no such topic")
    _fails(capsys, [*vo, str(two_pairs), "--left-topic", "/left/image", "--right-topic", "/left/image"],
           str(two_pairs), "--left-topic and --right-topic are both /left/image")

    def varying(bag, k, stamp, topic):
        size = (20, 32) if k < 2 else (22, 32)
        bag.write(topic, stamp, bag.image(stamp, "cam", np.zeros((*size, 3), np.uint8), "rgb8"))

    sizes = _write(tmp_path, "sizes", **{"/left/image": varying, "/right/image": _rgb()})
    _fails(capsys, [*vo, str(sizes)], str(sizes), "/left/image: image 2 is 22x32",
           "expected images of one size")
    odd = _write(tmp_path, "odd", **{t: lambda bag, k, s, topic: bag.write(
        topic, s, bag.image(s, "cam", np.zeros((20, 32, 4), np.uint8), "bgra8")) for t in ("/a0", "/a1")})
    _fails(capsys, [*vo, str(odd)], str(odd), "encoding 'bgra8'", "mono8, rgb8, bgr8, mono16")

    def bare(bag, k, stamp):
        for topic in ("/cam0/image", "/cam1/image"):
            bag.write(topic, stamp, bag.image(stamp, "cam", np.zeros((20, 32, 3), np.uint8), "rgb8"))

    no_info = Bag(tmp_path / "no-info.mcap", "mcap")
    for k, stamp in enumerate(stamps_of([0.0, 0.1])):
        bare(no_info, k, stamp)
    no_info.close()
    _fails(capsys, [*vo, str(no_info.path)], str(no_info.path), "no CameraInfo beside /cam0/image", "--calib")
    calib = kitti["tmp"] / "calib.txt"
    calib.write_text("P2: 30 0 15.5 0 0 30 9.5 0 0 0 1 0\nP3: 30 0 15.5 -15 0 30 9.5 0 0 0 1 0\n")
    assert main([*vo, str(no_info.path), "--calib", str(calib)]) == 0  # the same recording with --calib
    capsys.readouterr()
    for made in (out, out.with_suffix(".csv"), out.with_suffix(".json")):
        made.unlink()

    good = write_recording(tmp_path / "good.mcap", kitti["random"], compressed=True)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[:-200])  # no footer: a recording cut short
    _fails(capsys, [*vo, str(cut)], str(cut), "no footer", "cut short")
    truncated = tmp_path / "truncated.bag"
    truncated.write_bytes(write_recording(tmp_path / "whole.bag", kitti["random"], kind="ros1")
                          .read_bytes()[:5000])
    _fails(capsys, [*vo, str(truncated)], str(truncated), "cannot read the recording")
    not_a_bag = tmp_path / "notes.mcap"
    not_a_bag.write_text("not a recording\n")
    _fails(capsys, [*vo, str(not_a_bag)], str(not_a_bag), "cannot read the recording")
    assert not out.exists() and not out.with_suffix(".csv").exists()

    short = write_recording(tmp_path / "short.bag", kitti["random"], kind="ros1",
                            frames=lambda bag, k, s: bag.write("/odom", s, bag.odometry(
                                s, "odom", CAMERA_FRAME, kitti["poses"][k])) if k < 4 else None)
    cache = tmp_path / "cache"
    _fails(capsys, ["prepare", "--bag", str(short), "--prior-topic", "/odom", "--out", str(cache), "--size",
                    "10x16", "--no-progress"], str(short), "--prior-topic /odom: no pose within 10 ms of "
           "frame 4", "4 poses for 6 frames")
    _fails(capsys, ["prepare", "--bag", str(short), "--prior-topic", "/nowhere", "--out", str(cache)],
           "--prior-topic /nowhere: no such topic", "its pose topics: /odom")
    # Frame 2's pose missing, and a tolerance that lets frame 2 take a neighbour's: refused, not reused.
    gap = write_recording(tmp_path / "gap.bag", kitti["random"], kind="ros1",
                          frames=lambda bag, k, s: bag.write("/odom", s, bag.odometry(
                              s, "odom", CAMERA_FRAME, kitti["poses"][k])) if k != 2 else None)
    _fails(capsys, ["prepare", "--bag", str(gap), "--prior-topic", "/odom", "--stamp-tolerance", "0.15",
                    "--out", str(cache), "--size", "10x16", "--no-progress"], str(gap),
           "--prior-topic /odom: frames 1 and 2 both take the pose stamped", "expected a pose per frame")
    assert not cache.exists()

