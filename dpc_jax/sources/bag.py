"""A ROS recording as a stereo sequence: a ROS 1 ``.bag``, a ROS 2 bag folder (sqlite3 or MCAP storage),
a plain ``.mcap`` or ``.db3`` file, read with ``rosbags`` (docs/formats.md, "Recordings").

:func:`open_bag` makes the *index pass*: it reads the two image topics, the ``CameraInfo`` beside them,
the pose topics asked for, ``/tf_static`` and ``/tf``, and keeps of each image its header stamp (of a raw
image also its size and encoding); no image is decoded there but the first of a compressed topic (for
its size). The *frames pass* (:class:`BagFrames`) reads the image topics again, in order, and decodes
each image once, when it is used, so that memory does not grow with the recording's length.
``rosbags`` reads a message whole (a header cannot be read without its payload), so the image messages'
bytes come from storage in both passes; docs/formats.md says what each pass costs.

* **Topics.** Left and right are ``--left-topic``/``--right-topic``, or chosen when the recording holds
  exactly one pair of image topics whose names differ only by ``left``/``right`` or ``0``/``1``.
* **Frames.** Left and right images are paired by header stamp: each left image with the nearest right
  one when they are within ``tolerance`` seconds of each other and each is the other's nearest; an
  image without a partner is skipped and counted. Stamps that do not increase on a topic are refused.
  The sequence's times are the left stamps in seconds since the first pair's.
* **Calibration.** From the ``camera_info`` topic beside each image topic, else ``--calib FILE``
  (``dpc_jax.sources.bag_calibration``).
* **Poses.** A prior or ground-truth topic gives one pose per frame, the one nearest the left image's
  stamp within ``tolerance``. Poses describe the left camera: the pose's own frame (an odometry's or a
  transform's child frame, or ``pose_frame``) is the camera's frame id, or ``/tf_static`` and ``/tf`` link
  them and the pose is moved onto the camera (the chain at the frame's stamp), or ``pose_frame`` is the
  camera's frame id (they coincide).

Every problem is a ``ValueError`` of one line that names the recording, the topic and what was expected.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dpc_jax.data.frames import StereoFrame, checked_size
from dpc_jax.data.kitti import StereoSequence
from dpc_jax.data.poses_io import validate_poses
from dpc_jax.geometry.poses import invert_poses
from dpc_jax.sources import bag_images, bag_poses
from dpc_jax.sources.bag_calibration import calibration, info_topic
from dpc_jax.sources.bag_reader import BagError, open_reader, read_messages
from dpc_jax.sources.recording import BagOptions, Recording, Source

# A mono16 camera whose values use this many bits or fewer is noted: its 8-bit images come out dark.
LOW_BITS = 14
TF_STATIC, TF_MOVING = "/tf_static", "/tf"


def _stereo_names(left: str, right: str) -> bool:
    """Whether two topic names differ only by ``left``/``right`` or ``0``/``1`` at one place."""
    for a, b in (("left", "right"), ("0", "1")):
        for i in range(len(left)):
            if left.startswith(a, i) and right == left[:i] + b + left[i + len(a):]:
                return True
    return False


def _image_topics(path: Path, topics: dict[str, str], options: BagOptions) -> tuple[str, str]:
    images = sorted(t for t, kind in topics.items() if kind in bag_images.IMAGE_TYPES)
    listed = ", ".join(images) or "none"
    if options.left_topic is not None or options.right_topic is not None:
        if options.left_topic is None or options.right_topic is None:
            raise BagError(f"{path}: --left-topic and --right-topic go together; its image topics: {listed}")
        if options.left_topic == options.right_topic:
            raise BagError(f"{path}: --left-topic and --right-topic are both {options.left_topic}; expected "
                         f"the two cameras' topics (its image topics: {listed})")
        for option, topic in (("--left-topic", options.left_topic), ("--right-topic", options.right_topic)):
            if topic not in topics:
                raise BagError(f"{path}: {option} {topic}: no such topic; its image topics: {listed}")
            if topics[topic] not in bag_images.IMAGE_TYPES:
                raise BagError(f"{path}: {option} {topic} is {topics[topic]}; expected sensor_msgs/Image or "
                             f"CompressedImage (its image topics: {listed})")
        return options.left_topic, options.right_topic
    if not images:
        raise BagError(f"{path}: no image topic (sensor_msgs/Image or CompressedImage); its topics: "
                     f"{', '.join(sorted(topics)) or 'none'}")
    if len(images) == 1:
        raise BagError(f"{path}: one camera only ({images[0]}); expected the two image topics of a stereo "
                       "pair")
    pairs = [(a, b) for a in images for b in images if _stereo_names(a, b)]
    if len(pairs) != 1:
        found = "no stereo pair" if not pairs else f"{len(pairs)} stereo pairs"
        raise BagError(f"{path}: {found} among its image topics ({listed}); pass --left-topic and "
                     "--right-topic")
    return pairs[0]


@dataclass
class _Camera:
    """What the index pass keeps of one image topic."""

    topic: str
    stamps: list[int]
    size: tuple[int, int] | None = None
    frame_id: str = ""
    first: tuple[str, Any] | None = None  # the first message, for the size of a compressed one


def _pairs(left: np.ndarray, right: np.ndarray, tolerance_ns: int) -> np.ndarray:
    """int64 ``[N, 2]`` indices into ``left`` and ``right`` of the images paired by nearest stamp: mutual
    nearest neighbours within ``tolerance_ns`` (both stamp arrays increasing)."""
    if left.size == 0 or right.size == 0:
        return np.zeros((0, 2), np.int64)

    to_right = bag_poses.nearest(right, left)
    to_left = bag_poses.nearest(left, right)
    k = np.arange(left.size)
    keep = (to_left[to_right] == k) & (np.abs(right[to_right] - left) <= tolerance_ns)
    return np.stack([k[keep], to_right[keep]], axis=1).astype(np.int64)


def _increasing(path: Path, camera: _Camera, notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """The message numbers and header stamps (ns) of ``camera``'s images, increasing: an image whose stamp
    repeats the one before it is dropped, with a note (a driver that publishes a frame twice, or stamps two
    frames alike, gives no motion to pair it with); a stamp that goes back is one error line."""
    stamps = np.asarray(camera.stamps, np.int64)
    back = np.flatnonzero(np.diff(stamps) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise BagError(f"{path}: {camera.topic}: the header stamp of image {i} ({stamps[i] / 1e9:.9f} s) "
                       f"goes back from image {i - 1}'s ({stamps[i - 1] / 1e9:.9f} s); expected increasing "
                       "stamps")
    repeats = np.flatnonzero(np.diff(stamps) == 0) + 1
    if repeats.size:
        i = int(repeats[0])
        notes.append(f"{path}: {camera.topic}: {repeats.size} image(s) repeat the header stamp of the image "
                     f"before them (the first: image {i} at {stamps[i] / 1e9:.9f} s); the first image of "
                     "each stamp is kept")
    numbers = np.delete(np.arange(stamps.size, dtype=np.int64), repeats)
    return numbers, stamps[numbers]


def _pose_topic(
    path: Path, option: str, topic: str, samples: list[bag_poses.PoseSample], msgtype: str,
    stamps: np.ndarray, tolerance_ns: int, camera_frame: str, pose_frame: str | None,
    static: dict[bag_poses.Edge, np.ndarray], moving: dict[bag_poses.Edge, list[tuple[int, np.ndarray]]],
) -> tuple[np.ndarray, str]:
    """The poses of ``topic`` at the frames' left ``stamps`` as camera-to-world ``[N, 4, 4]``, and the world
    frame's id."""
    body = pose_frame
    if msgtype == bag_poses.TF:
        body = body or camera_frame
        samples = [s for s in samples if s.child == body]
        if not samples:
            raise BagError(f"{path}: {option} {topic}: no transform to frame {body!r}; pass --pose-frame "
                         "FRAME to name the frame whose transforms are the poses")
    where = f"{path}: {option} {topic}"
    if not samples:
        raise BagError(f"{where}: no pose; expected one per frame")
    body = body or samples[0].child
    if body is None:
        raise BagError(f"{where}: {msgtype} names no frame for its poses; pass --pose-frame {camera_frame} "
                       "if they are the left camera's poses (or the frame /tf_static and /tf link to it)")
    link = bag_poses.link(static, moving, body, camera_frame, stamps, tolerance_ns, where)
    if link is None:
        raise BagError(f"{where}: poses of frame {body!r}, images of frame {camera_frame!r}, and neither "
                     f"{TF_STATIC} nor {TF_MOVING} links them; pass --pose-frame {camera_frame} if the two "
                     "coincide")
    order = np.argsort([s.stamp for s in samples], kind="stable")
    pose_stamps = np.asarray([samples[i].stamp for i in order], np.int64)
    nearest, k = bag_poses.nearest_within(pose_stamps, stamps, tolerance_ns)
    if k is not None:
        raise BagError(f"{where}: no pose within {tolerance_ns / 1e6:g} ms of frame {k} (stamp "
                     f"{stamps[k] / 1e9:.9f} s); the topic holds {pose_stamps.size} poses for {stamps.size} "
                     "frames, expected one per frame")
    # Two frames taking one pose (a pose missing, a tolerance wider than half the frame interval) would
    # give a zero step and then a double one.
    shared = np.flatnonzero(np.diff(nearest) == 0)
    if shared.size:
        k = int(shared[0])
        raise BagError(f"{where}: frames {k} and {k + 1} both take the pose stamped "
                     f"{pose_stamps[nearest[k]] / 1e9:.9f} s (the nearest within {tolerance_ns / 1e6:g} ms); "
                     "expected a pose per frame (is one missing, or --stamp-tolerance wider than half the "
                     "frame interval?)")
    poses = np.stack([samples[order[i]].matrix @ link[k] for k, i in enumerate(nearest)])
    return validate_poses(poses, where), samples[0].parent


def open_source(source: Source) -> Recording:
    """The recording ``source.path`` with ``source.bag``'s options (:func:`open_bag`)."""
    options = source.bag or BagOptions(source.path)
    return open_bag(options)


def open_bag(options: BagOptions) -> Recording:
    """Open a recording (module docstring); ``ValueError`` of one line for every problem."""
    path = options.path
    if not math.isfinite(options.tolerance) or options.tolerance <= 0:
        raise BagError(f"--stamp-tolerance {options.tolerance}: expected a positive number of seconds")
    tolerance_ns = round(options.tolerance * 1e9)
    with open_reader(path) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        left_topic, right_topic = _image_topics(path, topics, options)
        cameras = (_Camera(left_topic, []), _Camera(right_topic, []))
        by_topic = {camera.topic: camera for camera in cameras}
        info_topics = {}
        if options.calib is None:
            info_topics = {t: info_topic(t, topics) for t in (left_topic, right_topic)}
        pose_topics = {}
        for option, topic in (("--prior-topic", options.prior_topic), ("--gt-topic", options.gt_topic)):
            if topic is None:
                continue
            if topics.get(topic) not in bag_poses.POSE_TYPES:
                listed = ", ".join(sorted(t for t, kind in topics.items() if kind in bag_poses.POSE_TYPES))
                what = "no such topic" if topic not in topics else f"a {topics[topic]} topic"
                raise BagError(f"{path}: {option} {topic}: {what}; expected nav_msgs/Odometry, PoseStamped, "
                             f"PoseWithCovarianceStamped or /tf (its pose topics: {listed or 'none'})")
            pose_topics[option] = topic
        wanted = {left_topic, right_topic, *pose_topics.values(),
                  *(t for t in info_topics.values() if t is not None)}
        wanted |= {t for t in (TF_STATIC, TF_MOVING) if pose_topics and topics.get(t) == bag_poses.TF}
        infos: dict[str, tuple[str, Any]] = {}
        samples: dict[str, list[bag_poses.PoseSample]] = {t: [] for t in pose_topics.values()}
        static: dict[bag_poses.Edge, np.ndarray] = {}
        moving: dict[bag_poses.Edge, list[tuple[int, np.ndarray]]] = {}
        connections = [c for c in reader.connections if c.topic in wanted]
        for connection, number, msg in read_messages(reader, path, connections):
            topic, msgtype = connection.topic, connection.msgtype
            camera = by_topic.get(topic)
            if camera is not None:
                _index_image(path, camera, number, msgtype, msg)
            for image_topic, beside in info_topics.items():
                if topic == beside and image_topic not in infos:
                    infos[image_topic] = (topic, msg)
            if topic in samples:
                samples[topic].extend(bag_poses.samples(msgtype, msg, f"{path}: {topic}"))
            tf = topic in (TF_STATIC, TF_MOVING)
            for s in bag_poses.samples(msgtype, msg, f"{path}: {topic}") if tf else []:
                if topic == TF_STATIC:
                    static[(s.parent, s.child or "")] = s.matrix
                else:
                    moving.setdefault((s.parent, s.child or ""), []).append((s.stamp, s.matrix))
    for camera in cameras:
        if not camera.stamps:
            raise BagError(f"{path}: {camera.topic}: no image; expected the images of one camera of the pair")
    notes: list[str] = []
    for camera in cameras:
        assert camera.first is not None  # it has images
        bits = bag_images.mono16_bits(camera.first[0], camera.first[1], f"{path}: {camera.topic}")
        if bits is not None and bits <= LOW_BITS:
            notes.append(f"{path}: {camera.topic}: the mono16 values of its first image use {bits} bits, and "
                         "8-bit images keep the high byte, so they come out dark; shift the data to the high "
                         "bits")
    (left_numbers, left_stamps), (right_numbers, right_stamps) = (_increasing(path, camera, notes)
                                                                  for camera in cameras)
    size = cameras[0].size or _first_size(path, cameras[0])
    right_size = cameras[1].size or _first_size(path, cameras[1])
    if right_size != size:
        raise BagError(f"{path}: {right_topic} holds {right_size[0]}x{right_size[1]} images, {left_topic} "
                     f"{size[0]}x{size[1]}; expected one size for both cameras")
    pairs = _pairs(left_stamps, right_stamps, tolerance_ns)  # into the kept images
    skipped = (left_stamps.size - pairs.shape[0], right_stamps.size - pairs.shape[0])
    if any(skipped):
        notes.append(f"{path}: {skipped[0]} left and {skipped[1]} right images without a partner within "
                     f"{tolerance_ns / 1e6:g} ms skipped ({pairs.shape[0]} stereo frames)")
    if pairs.shape[0] < 2:
        raise BagError(f"{path}: {pairs.shape[0]} stereo frames of {left_topic} and {right_topic} within "
                     f"{tolerance_ns / 1e6:g} ms of each other; expected at least 2 (--stamp-tolerance)")
    K, baseline, maps, calib_files = calibration(path, infos, (left_topic, right_topic), size,
                                                 options.calib, notes)
    stamps = left_stamps[pairs[:, 0]]
    camera_frame = cameras[0].frame_id
    poses: dict[str, np.ndarray] = {}
    world_frame = "world"
    for option, topic in pose_topics.items():
        poses[option], parent = _pose_topic(
            path, option, topic, samples[topic], topics[topic], stamps, tolerance_ns, camera_frame,
            options.pose_frame, static, moving)
        if option == "--prior-topic":
            world_frame = parent
        sideways = _sideways(poses[option])
        if sideways is not None:
            notes.append(f"{path}: {option} {topic}: its steps point along the camera's {sideways} axis more "
                         f"than along z (forward in an optical frame); is {camera_frame!r} the camera's "
                         "optical frame (z forward, x right, y down)?")
    pair_stamps = np.stack([stamps, right_stamps[pairs[:, 1]]], axis=1)
    gt = poses.get("--gt-topic")
    numbers = np.stack([left_numbers[pairs[:, 0]], right_numbers[pairs[:, 1]]], axis=1)
    frames = BagFrames(path, (left_topic, right_topic), numbers, pair_stamps, maps,
                       "" if gt is None else hashlib.sha256(np.ascontiguousarray(gt).tobytes()).hexdigest())
    name = path.stem if path.is_file() else path.name
    sequence = StereoSequence(name=name, images=frames, K=K, baseline=baseline, image_size=size,
                              times=(stamps - stamps[0]) / 1e9, poses=poses.get("--gt-topic"),
                              sources=calib_files)
    return Recording(sequence, poses.get("--prior-topic"), int(stamps[0]), camera_frame, world_frame,
                     tuple(notes))


def _sideways(poses: np.ndarray) -> str | None:
    """The camera axis (``x`` or ``y``) that a trajectory's mean step points along more than along z, or
    None: a camera that moves forward steps along z in its optical frame; a body frame's x forward would
    show here as x."""
    steps = (invert_poses(poses[:-1]) @ poses[1:])[:, :3, 3].mean(axis=0)
    axis = int(np.argmax(np.abs(steps)))
    return None if axis == 2 or not np.abs(steps).max() > 0 else "xy"[axis]


def _index_image(path: Path, camera: _Camera, number: int, msgtype: str, msg: Any) -> None:
    """Keep an image message's stamp; check its encoding (and, raw, its size) against the first one's."""
    where = f"{path}: {camera.topic}"
    problem = bag_images.encoding_problem(msgtype, msg)
    if problem is not None:
        raise BagError(f"{where}: image {number} has {problem}")
    camera.stamps.append(bag_poses.stamp_ns(msg.header))
    if number == 0:
        camera.frame_id = msg.header.frame_id
        camera.first = (msgtype, msg)
    if msgtype == bag_images.IMAGE:
        size = bag_images.raw_size(msg)
        if camera.size is None:
            camera.size = size
        elif size != camera.size:
            raise BagError(f"{where}: image {number} is {size[0]}x{size[1]}, image 0 {camera.size[0]}x"
                         f"{camera.size[1]}; expected images of one size")


def _first_size(path: Path, camera: _Camera) -> tuple[int, int]:
    """The size of a compressed topic's first image (decoded)."""
    assert camera.first is not None
    msgtype, msg = camera.first
    image = bag_images.decode(msgtype, msg, True, f"{path}: {camera.topic} image 0")
    return int(image.shape[0]), int(image.shape[1])


@dataclass(frozen=True)
class BagFrames:
    """The stereo frames of a recording: message numbers ``[N, 2]`` on the left and right topics, their
    header stamps (ns, ``[N, 2]``) and the rectification maps of distorted cameras (None: rectified)."""

    path: Path
    topics: tuple[str, str]
    numbers: np.ndarray
    stamps: np.ndarray
    maps: tuple[Any, Any] | None = None
    # A digest of the ground truth read from a pose topic (none: ""): held in memory, not in a file the
    # cache hashes, so it is part of the frames' identity.
    ground_truth: str = ""

    def __len__(self) -> int:
        return int(self.numbers.shape[0])

    def select(self, start: int, stop: int) -> BagFrames:
        return replace(self, numbers=self.numbers[start:stop], stamps=self.stamps[start:stop])

    def stream(self, size: tuple[int, int], indices: Sequence[int] | None = None) -> Iterator[StereoFrame]:
        chosen = list(range(len(self))) if indices is None else list(indices)
        if not chosen:
            return
        wanted = self.numbers[chosen]
        needed = ({int(n) for n in wanted[:, 0]}, {int(n) for n in wanted[:, 1]})
        held: dict[tuple[int, int], tuple[str, Any]] = {}
        j = 0
        with open_reader(self.path) as reader:
            connections = [c for c in reader.connections if c.topic in self.topics]
            for connection, number, msg in read_messages(reader, self.path, connections):
                side = self.topics.index(connection.topic)
                if number in needed[side]:
                    held[(side, number)] = (connection.msgtype, msg)
                while j < len(chosen) and all((side, int(wanted[j, side])) in held for side in (0, 1)):
                    left, right = (held.pop((side, int(wanted[j, side]))) for side in (0, 1))
                    yield self._frame(chosen[j], left, right, size)
                    j += 1
                if j == len(chosen):
                    return
        raise BagError(f"{self.path}: the recording holds fewer images than its index said (frame "
                       f"{chosen[j]} missing); was it changed while read?")

    def _frame(
        self, index: int, left: tuple[str, Any], right: tuple[str, Any], size: tuple[int, int]
    ) -> StereoFrame:
        where = f"{self.path}: {self.topics[0]} at {self.stamps[index][0] / 1e9:.9f} s"
        maps = self.maps

        def read(grey: bool) -> tuple[np.ndarray, np.ndarray]:
            images = []
            for side, (msgtype, msg) in enumerate((left, right)):
                at = f"{self.path}: {self.topics[side]} at {self.stamps[index][side] / 1e9:.9f} s"
                image = checked_size(bag_images.decode(msgtype, msg, grey, at), size, at)
                if maps is not None and maps[side][0] is not None:
                    image = cv2.remap(image, maps[side][0], maps[side][1], cv2.INTER_LINEAR)
                images.append(image)
            return images[0], images[1]

        return StereoFrame(index, where, read)

    def identity(self) -> list[str]:
        files = sorted(p for p in self.path.rglob("*") if p.is_file()) if self.path.is_dir() else [self.path]
        texts = []
        for file in files:
            st = file.stat()
            texts.append(f"{file.resolve()}:{st.st_size}:{st.st_mtime_ns}")
        frames = hashlib.sha256(np.ascontiguousarray(self.numbers).tobytes()).hexdigest()
        # How the images are remapped (rectified here, or used as they are) is part of what a cache holds.
        remap = hashlib.sha256()
        for side in self.maps or ():
            for table in side:
                remap.update(b"none" if table is None else np.ascontiguousarray(table).tobytes())
        return [*texts, f"topics {self.topics[0]} {self.topics[1]} frames {frames}",
                f"remap {'none' if self.maps is None else remap.hexdigest()}",
                f"ground truth {self.ground_truth or 'none'}"]

    def locations(self) -> dict[str, str]:
        return {"left_images": f"{self.path.resolve()} {self.topics[0]}",
                "right_images": f"{self.path.resolve()} {self.topics[1]}"}


def read_pose_topic(path: Path, topic: str) -> tuple[np.ndarray, np.ndarray, str | None]:
    """Every pose of ``topic`` (``nav_msgs/Odometry``, ``PoseStamped``, ``PoseWithCovarianceStamped``) in
    a recording, by header stamp: ``(times [N] s, poses [N, 4, 4], frame)``, as a timed trajectory file
    gives them (``dpc-jax evaluate``), ``frame`` the frame they are the poses of (an odometry's first
    ``child_frame_id``; None where the messages name none); ``ValueError`` of one line naming the
    recording and the topic."""
    kinds = (bag_poses.ODOMETRY, bag_poses.POSE, bag_poses.POSE_COVARIANCE)
    with open_reader(path) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        if topics.get(topic) not in kinds:
            listed = ", ".join(sorted(t for t, kind in topics.items() if kind in kinds)) or "none"
            what = "no such topic" if topic not in topics else f"a {topics[topic]} topic"
            raise BagError(f"{path}: {topic}: {what}; expected nav_msgs/Odometry, PoseStamped or "
                         f"PoseWithCovarianceStamped (its pose topics: {listed})")
        connections = [c for c in reader.connections if c.topic == topic]
        samples = [s for _, _, msg in read_messages(reader, path, connections)
                   for s in bag_poses.samples(topics[topic], msg, f"{path}: {topic}")]
    if len(samples) < 2:
        raise BagError(f"{path}: {topic}: {len(samples)} pose; expected a trajectory of at least 2")
    order = np.argsort([s.stamp for s in samples], kind="stable")
    stamps = np.asarray([samples[i].stamp for i in order], np.int64)
    poses = validate_poses(np.stack([samples[i].matrix for i in order]), f"{path}: {topic}")
    return stamps / 1e9, poses, samples[0].child or None
