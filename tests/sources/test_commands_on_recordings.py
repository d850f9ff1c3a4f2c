"""Every command on every kind of recording: `vo`, `prepare`, `correct --out corrected.mcap`,
`live --realtime` and `evaluate` with a recording's topics, on a ROS 1 bag, a ROS 2 bag of sqlite3 and
of MCAP storage and a plain MCAP file (written by ``rosbags``' own writers, tests/recordings.py), with
raw and PNG-compressed images, each giving what the same frames give through the KITTI layout; and how
often each command reads a recording's image messages (the index pass, then each frames pass) and
decodes each image.

One module fixture: a 6-frame odometry sequence of random 48×72 images, a stored untrained Stereo DPC
run at 32×48 (as tests/cli/test_live_cli.py's, one compilation for the module) and the layout's outputs
of every command, made once.
"""

from __future__ import annotations

import contextlib
import json
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from recordings import CAMERA_FRAME, KINDS, stamps_of, write_recording
from support import write_odometry, write_stored_run

from dpc_jax.cli import main
from dpc_jax.data.poses_io import read_trajectory

FRAMES = 6
SUFFIX = {"ros1": ".bag", "mcap": ".mcap", "sqlite3": "", "mcap-folder": ""}
# The cases of every kind × image encoding that run outside `-m slow`: one of each storage family.
FAST = {("ros1", False), ("mcap", True)}


def _poses(path: Path) -> np.ndarray:
    return read_trajectory(path, "kitti")


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict:
    from dpc_jax.pipelines import protocol as dpc_protocol
    from dpc_jax.training.train_config import REFERENCE, TrainConfig

    tmp = tmp_path_factory.mktemp("commands")
    written = write_odometry(tmp / "kitti", "00", n=FRAMES, size=(48, 72))
    kitti, poses_file = tmp / "kitti", tmp / "kitti" / "poses" / "00.txt"
    # The published initialisation (REFERENCE) gives an untrained network a correction that is not zero.
    config = TrainConfig(method="stereo_dpc", **{**dpc_protocol.SMOKE, **REFERENCE},
                         cache_root=str(tmp / "cache"), train_sequences=("00",), validation_sequences=("05",))
    write_stored_run(tmp / "run", config, {1: (7, 0.5, 0, -1e-4)})
    layout = ["--kitti-odometry", str(kitti), "--sequence", "00"]
    out = tmp / "layout"
    out.mkdir()
    assert main(["vo", *layout, "--out", str(out / "vo.txt"), "--no-progress"]) == 0
    assert main(["prepare", *layout, "--prior", str(poses_file), "--out", str(out / "cache"), "--size",
                 "24x36", "--no-progress"]) == 0
    run = ["--checkpoint", str(tmp / "run")]
    assert main(["correct", *run, *layout, "--prior", str(poses_file), "--out", str(out / "corrected.txt"),
                 "--no-progress"]) == 0
    files = tmp / "kitti" / "sequences" / "00"
    records = [f"{t:.3f} {files}/image_2/{k:06d}.png {files}/image_3/{k:06d}.png "
               + " ".join(f"{v:.17g}" for v in pose[:3].ravel()) + "\n"
               for k, (t, pose) in enumerate(zip(written["times"], written["poses"], strict=True))]
    (tmp / "records.txt").write_text("".join(records))
    assert main(["live", *run, "--calib", str(files / "calib.txt"), "--image-size", "48x72", "--records",
                 str(tmp / "records.txt"), "--out", str(out / "live.txt")]) == 0
    return {"tmp": tmp, "kitti": kitti, "run": run, "poses": written["poses"], "out": out,
            "poses_file": poses_file}


@contextlib.contextmanager
def _counted(monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, Counter]]:
    """Count, by topic, the image messages ``rosbags`` reads from storage and the images dpc_jax decodes."""
    from rosbags.highlevel import AnyReader

    from dpc_jax.sources import bag_images

    counts: dict[str, Counter] = {"read": Counter(), "decoded": Counter()}
    messages, decode = AnyReader.messages, bag_images.decode

    def counted_messages(self: Any, *args: Any, **kwargs: Any) -> Iterator[Any]:
        for connection, stamp, raw in messages(self, *args, **kwargs):
            if connection.msgtype in bag_images.IMAGE_TYPES:
                counts["read"][connection.topic] += 1
            yield connection, stamp, raw

    def counted_decode(msgtype: str, msg: Any, grey: bool, where: str) -> np.ndarray:
        counts["decoded"][where.split(": ")[1].split(" ")[0]] += 1
        return decode(msgtype, msg, grey, where)

    monkeypatch.setattr(AnyReader, "messages", counted_messages)
    monkeypatch.setattr(bag_images, "decode", counted_decode)
    yield counts
    monkeypatch.undo()


def _cases() -> list[Any]:
    return [pytest.param(kind, compressed, id=f"{kind}-{'png' if compressed else 'raw'}",
                         marks=() if (kind, compressed) in FAST else pytest.mark.slow)
            for kind in KINDS for compressed in (False, True)]


@pytest.mark.parametrize("kind,compressed", _cases())
def test_every_command_on_a_recording_gives_what_the_kitti_layout_gives(
    world: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
    kind: str, compressed: bool,
) -> None:
    from rosbags.highlevel import AnyReader

    layout = world["out"]
    rec = write_recording(tmp_path / f"rec{SUFFIX[kind]}", world["kitti"], kind=kind, compressed=compressed,
                          poses={"/odom": world["poses"]})
    bag = ["--bag", str(rec)]
    # Each image message read twice (index and frames pass), each image decoded once; a compressed
    # topic's first image once more in the index pass, for its size.
    once = {topic: FRAMES + int(compressed) for topic in _image_topics(rec)}
    twice = dict.fromkeys(once, 2 * FRAMES)

    with _counted(monkeypatch) as counts:
        assert main(["vo", *bag, "--out", str(tmp_path / "vo.txt"), "--no-progress"]) == 0
    assert (tmp_path / "vo.txt").read_bytes() == (layout / "vo.txt").read_bytes()
    assert counts == {"read": twice, "decoded": once}

    with _counted(monkeypatch) as counts:
        assert main(["prepare", *bag, "--prior", str(world["poses_file"]), "--gt", str(world["poses_file"]),
                     "--out", str(tmp_path / "cache"), "--size", "24x36", "--no-progress"]) == 0
    assert counts == {"read": twice, "decoded": once}
    ours, theirs = tmp_path / "cache" / rec.stem, layout / "cache" / "00"
    arrays = sorted(p.name for p in theirs.glob("*.npy"))
    assert len(arrays) >= 5 and arrays == sorted(p.name for p in ours.glob("*.npy"))
    for array in arrays:
        assert (ours / array).read_bytes() == (theirs / array).read_bytes(), array

    corrected = tmp_path / "corrected.mcap"
    with _counted(monkeypatch) as counts:
        assert main(["correct", *world["run"], *bag, "--prior-topic", "/odom", "--out", str(corrected),
                     "--no-progress"]) == 0
    # The run's cache and its judge's (the same frames at 48×72): the frames pass twice.
    assert counts == {"read": dict.fromkeys(once, 3 * FRAMES),
                      "decoded": {topic: 2 * FRAMES + int(compressed) for topic in once}}
    with AnyReader([corrected]) as reader:
        assert {c.topic: (c.msgtype, c.msgcount) for c in reader.connections} == {
            topic: ("nav_msgs/msg/Odometry", FRAMES) for topic in ("/dpc/odometry", "/dpc/prior")}
        read = [(stamp, reader.deserialize(raw, connection.msgtype)) for connection, stamp, raw
                in reader.messages() if connection.topic == "/dpc/odometry"]
    assert [stamp for stamp, _ in read] == stamps_of(np.arange(FRAMES) * 0.1)
    assert {(msg.header.frame_id, msg.child_frame_id) for _, msg in read} == {("odom", CAMERA_FRAME)}
    # The prior through quaternions: the layout's corrected poses to rounding.
    np.testing.assert_allclose(np.stack([_matrix(msg.pose.pose) for _, msg in read]),
                               _poses(layout / "corrected.txt"), atol=1e-9)
    # evaluate with the recordings' topics: the metrics of the same poses as KITTI text files.
    from_bag = tmp_path / "from_bag.txt"
    assert main(["evaluate", "--gt", f"{corrected}:/dpc/odometry", "--est", f"{rec}:/odom", "--json",
                 str(from_bag.with_suffix(".json"))]) == 0
    assert main(["evaluate", "--gt", str(layout / "corrected.txt"), "--est", str(world["poses_file"]),
                 "--json", str(tmp_path / "from_files.json")]) == 0
    metrics = [json.loads(p.read_text())["estimates"] for p in (from_bag.with_suffix(".json"),
                                                                tmp_path / "from_files.json")]
    (bag_metrics,), (file_metrics,) = (m.values() for m in metrics)
    numbers = [key for key, value in file_metrics.items() if isinstance(value, float)]
    assert len(numbers) >= 4, file_metrics
    for key in numbers:
        assert bag_metrics[key] == pytest.approx(file_metrics[key], rel=1e-9, abs=1e-12), key

    with _counted(monkeypatch) as counts:
        assert main(["live", *world["run"], *bag, "--prior-topic", "/odom", "--realtime", "10", "--out",
                     str(tmp_path / "live.txt")]) == 0
    assert counts == {"read": twice, "decoded": once}
    np.testing.assert_allclose(_poses(tmp_path / "live.txt"), _poses(layout / "live.txt"), atol=1e-12)
    capsys.readouterr()


def _image_topics(rec: Path) -> list[str]:
    from rosbags.highlevel import AnyReader

    with AnyReader([rec]) as reader:
        return [c.topic for c in reader.connections
                if c.msgtype in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")]



def _matrix(pose: Any) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    matrix = np.eye(4)
    q, p = pose.orientation, pose.position
    matrix[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    matrix[:3, 3] = [p.x, p.y, p.z]
    return matrix
