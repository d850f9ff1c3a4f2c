"""``dpc-jax vo --correct`` and ``dpc-jax live``: each corrected pose written as one line the moment it
is made, the same poses as the library's live corrector, the prior beside it as ``dpc-jax vo`` writes it,
missed deadlines under ``--realtime``, Ctrl-C, and bad input.

Everything runs in-process through ``dpc_jax.cli.main`` on a 6-frame odometry sequence of random 48×72
images and a stored, untrained Stereo DPC run of the small preset at 32×48 (one compilation for the
module). Streams are FIFOs fed by a thread while the command runs in the main thread, so that a real
SIGINT reaches it there.
"""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from support import write_odometry

from dpc_jax.cli import main
from dpc_jax.pipelines import protocol as dpc_protocol

FRAMES = 6
COLUMNS = 18


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The sequence, its records (the ground truth as an external VO's poses), the run, and a copy of the
    run whose stored config says 64×96 (larger than the images; only its config is read)."""
    from support import write_stored_run

    from dpc_jax.data.kitti import open_odometry
    from dpc_jax.training.train_config import REFERENCE, TrainConfig

    tmp = tmp_path_factory.mktemp("live_cli")
    written = write_odometry(tmp / "kitti", "00", n=FRAMES, size=(48, 72))
    sequence = open_odometry(tmp / "kitti", "00")
    # The published initialisation (REFERENCE) gives an untrained network a correction that is not zero.
    config = TrainConfig(method="stereo_dpc", **{**dpc_protocol.SMOKE, **REFERENCE},
                         cache_root=str(tmp / "cache"), train_sequences=("00",), validation_sequences=("05",))
    write_stored_run(tmp / "run", config, {1: (7, 0.5, 0, -1e-4)})
    shutil.copytree(tmp / "run", tmp / "big_run")
    stored = tmp / "big_run" / "checkpoints" / "config.json"
    record = json.loads(stored.read_text())
    record["image_size"] = [64, 96]
    stored.write_text(json.dumps(record))
    files = sequence.images
    records = [f"{t:.3f} {left} {right} " + " ".join(f"{v:.17g}" for v in pose[:3].ravel()) + "\n"
               for t, left, right, pose in zip(written["times"], files.left_paths, files.right_paths,
                                               written["poses"], strict=True)]
    (tmp / "records.txt").write_text("".join(records))
    return {"tmp": tmp, "kitti": tmp / "kitti", "sequence": sequence, "run": tmp / "run",
            "big_run": tmp / "big_run", "records": records, "poses": written["poses"],
            "calib": tmp / "kitti" / "sequences" / "00" / "calib.txt"}


def _live_args(world: dict, out: Path, *more: object) -> list[str]:
    return ["live", "--checkpoint", str(world["run"]), "--calib", str(world["calib"]),
            "--image-size", "48x72", "--out", str(out), *map(str, more)]


def _poses(path: Path) -> np.ndarray:
    """Every line of a KITTI pose file, each parsed to 12 numbers (a half line fails here)."""
    rows = [np.array([float(v) for v in line.split()]) for line in path.read_text().splitlines()]
    assert all(row.shape == (12,) for row in rows), rows
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3] = np.reshape(rows, (-1, 3, 4))
    return poses


def _rows(path: Path) -> list[dict[str, str]]:
    text = path.read_text()
    assert text.endswith("\n")
    rows = list(csv.DictReader(text.splitlines()))
    assert all(len(row) == COLUMNS and None not in row for row in rows), rows
    return rows


def _reference(world: dict, *, force: bool, priors: np.ndarray | None, frames: int = FRAMES) -> list:
    """The library's live corrector on the same pairs: with ``priors`` the external VO's poses, else its
    own VO on the pairs decoded in grey as ``dpc-jax vo`` decodes them."""
    from dpc_jax.correction.live import Calibration, LiveCorrector
    from dpc_jax.data.kitti import load_image

    sequence = world["sequence"]
    first = None if priors is not None else world["poses"][0]
    live = LiveCorrector(world["run"], Calibration.of(sequence), force=force, first_pose=first, ahead=False)
    out = []
    files = sequence.images
    for k, (left, right) in enumerate(zip(files.left_paths[:frames], files.right_paths[:frames],
                                          strict=True)):
        grey = (load_image(left, grey=True), load_image(right, grey=True))
        prior = None if priors is None else priors[k]
        out.append(live(load_image(left), load_image(right), prior, grey=grey))
    return out


def test_vo_correct_writes_the_live_correctors_poses_with_their_states_and_the_prior_of_vo(
    world: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Forced, so that every pose but the first is corrected: the poses are those of the library's live
    corrector running its own VO; the prior beside them is `dpc-jax vo`'s trajectory, byte for byte,
    with the same record; one CSV row per frame says which state made its pose."""
    out = tmp_path / "live.txt"
    common = ["vo", "--kitti-odometry", str(world["kitti"]), "--sequence", "00", "--start", "gt"]
    assert main([*common, "--correct", str(world["run"]), "--force", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    reference = _reference(world, force=True, priors=None)
    np.testing.assert_allclose(_poses(out), np.stack([f.pose for f in reference]), atol=1e-9)
    assert np.abs(_poses(out) - _poses(tmp_path / "live.prior.txt")).max() > 1e-6  # the correction moved them
    assert main([*common, "--out", str(tmp_path / "plain.txt")]) == 0
    assert (tmp_path / "live.prior.txt").read_bytes() == (tmp_path / "plain.txt").read_bytes()
    assert json.loads((tmp_path / "live.prior.json").read_text()) == json.loads(
        (tmp_path / "plain.json").read_text())
    rows = _rows(tmp_path / "live.csv")
    assert [row["frame"] for row in rows] == [str(k) for k in range(FRAMES)]
    assert [row["state"] for row in rows] == ["start"] + ["forced"] * 5
    assert all(f.forced for f in reference)
    assert rows[0]["inliers"] == ""
    assert all(row["vo_status"] in ("ok", "constant_velocity") for row in rows[1:])
    stages = ("read", "vo", "prepare", "network", "measure")
    for row in rows:  # the stages are parts of the frame's latency
        assert float(row["latency_ms"]) >= sum(float(row[f"{name}_ms"] or 0) for name in stages)
    summary = json.loads((tmp_path / "live.json").read_text())
    assert summary["states"] == {"start": 1, "forced": 5} and summary["source_frames"] == [0, FRAMES]
    # The VO's rate printed is its pairs over its time, frame 0's included, as the CSV gives them.
    rate = float(re.search(r"VO ([\d.]+) frames/s alone", printed)[1])
    assert rate == pytest.approx((FRAMES - 1) / sum(1e-3 * float(row["vo_ms"]) for row in rows), rel=0.01)
    assert "states: forced 5, start 1" in printed and "vs ground truth, corrected: m-ATE" in printed


def _lines_in(path: Path) -> int:
    try:
        return path.read_text().count("\n")
    except FileNotFoundError:
        return 0


def _wait_for(condition: Callable[[], bool], seconds: float = 120.0) -> bool:
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def test_vo_correct_flushes_each_line_when_its_frame_is_done(world: dict, tmp_path: Path) -> None:
    """Into a FIFO at 10 Hz: a reader sees the six lines arrive over at least the 0.5 s the frames span,
    not together at the end; the CSV's arrival times are the camera's (k / 10 s) and its missed flags
    say whether each pose came after the next frame was due."""
    fifo = tmp_path / "poses"
    os.mkfifo(fifo)
    seen: list[tuple[float, str]] = []

    def read() -> None:
        with open(fifo) as stream:
            seen.extend((time.monotonic(), line) for line in stream)

    reader = threading.Thread(target=read)
    reader.start()
    status = main(["vo", "--kitti-odometry", str(world["kitti"]), "--sequence", "00", "--correct",
                   str(world["run"]), "--realtime", "10", "--out", str(fifo),
                   "--csv", str(tmp_path / "c.csv")])
    reader.join(timeout=60)
    assert status == 0 and len(seen) == FRAMES
    assert seen[-1][0] - seen[0][0] >= 0.45, [t - seen[0][0] for t, _ in seen]
    assert all(len(line.split()) == 12 for _, line in seen)
    rows = _rows(tmp_path / "c.csv")
    for k, row in enumerate(rows):
        assert float(row["arrival_s"]) == pytest.approx(k / 10, abs=1e-6)
        assert float(row["written_s"]) >= float(row["arrival_s"])
        assert row["missed"] == str(int(float(row["written_s"]) > (k + 1) / 10))
    assert not (tmp_path / "poses.json").exists()  # nothing is made beside a stream


def test_live_replays_a_recording_and_reports_the_frames_that_missed_their_deadline(
    world: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """At 10 kHz every pair (a network pass) misses its 0.1 ms; the summary, the JSON and the CSV name the
    same frames. Five pairs are too few for any sequential test to accept, so each pose is the external
    VO's own, composed from its first."""
    out = tmp_path / "live.txt"
    assert main(_live_args(world, out, "--records", world["tmp"] / "records.txt", "--realtime", "10000")) == 0
    printed = capsys.readouterr().out
    rows = _rows(tmp_path / "live.csv")
    missed = [int(row["frame"]) for row in rows if row["missed"] == "1"]
    assert set(range(1, FRAMES)) <= set(missed)
    for k, row in enumerate(rows):
        assert row["missed"] == str(int(float(row["written_s"]) > (k + 1) / 1e4))
    assert f"realtime 10000 Hz: {len(missed)} of {FRAMES} frames missed their deadline" in printed
    assert json.loads((tmp_path / "live.json").read_text())["missed_deadlines"] == missed
    assert [row["state"] for row in rows] == ["start"] + ["prior"] * 5
    assert [row["time_s"] for row in rows] == [f"{0.1 * k:.6f}" for k in range(FRAMES)]
    np.testing.assert_allclose(_poses(out), world["poses"], atol=1e-9)
    reference = _reference(world, force=False, priors=world["poses"])
    np.testing.assert_allclose(_poses(out), np.stack([f.pose for f in reference]), atol=1e-9)


def test_live_on_a_recording_writes_what_its_records_give(
    world: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The sequence as a recording written by rosbags (rgb8 images, CameraInfo, the external VO's poses as
    nav_msgs/Odometry): `live --bag --prior-topic` corrects the frames the records name, with their poses,
    to the same poses as `live --records`; its CSV has the recording's times."""
    from recordings import write_recording

    recording = write_recording(tmp_path / "rec.bag", world["kitti"], kind="ros1",
                                poses={"/vo": world["poses"]})
    assert main(_live_args(world, tmp_path / "records.txt", "--records", world["tmp"] / "records.txt",
                           "--force")) == 0
    bag = ["live", "--checkpoint", str(world["run"]), "--bag", str(recording), "--prior-topic", "/vo",
           "--force", "--realtime", "10", "--out", str(tmp_path / "bag.txt")]
    assert main(bag) == 0
    printed = capsys.readouterr().out
    assert f"{recording}: {FRAMES} frames corrected live" in printed
    np.testing.assert_allclose(_poses(tmp_path / "bag.txt"), _poses(tmp_path / "records.txt"), atol=1e-12)
    assert [row["time_s"] for row in _rows(tmp_path / "bag.csv")] == [f"{0.1 * k:.6f}" for k in range(FRAMES)]
    assert main([*bag[:-2], "--prior-topic", "/nowhere", "--out", str(tmp_path / "none.txt")]) == 1
    assert "--prior-topic /nowhere: no such topic" in capsys.readouterr().err


def test_live_replays_a_recording_at_its_own_stamps(
    world: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`live --bag REC --realtime` (no HZ): frame k arrives when the recording's header stamps say, its
    stamps irregular here (0.05 s to 0.2 s apart), and misses its deadline when its pose is written after
    the next frame's stamp; `vo --correct --realtime` keeps the layout's times the same way; records,
    which have no stamps, are refused it before JAX starts."""
    from recordings import write_recording

    kitti = tmp_path / "kitti"
    shutil.copytree(world["kitti"], kitti)
    stamps = [0.0, 0.05, 0.25, 0.3, 0.35, 0.5]
    (kitti / "sequences" / "00" / "times.txt").write_text("".join(f"{t:.6e}\n" for t in stamps))
    recording = write_recording(tmp_path / "rec.mcap", kitti, poses={"/vo": world["poses"]})
    out = tmp_path / "bag.txt"
    assert main(["live", "--checkpoint", str(world["run"]), "--bag", str(recording), "--prior-topic", "/vo",
                 "--realtime", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    rows = _rows(tmp_path / "bag.csv")
    assert [float(row["time_s"]) for row in rows] == pytest.approx(stamps, abs=1e-6)
    for k, row in enumerate(rows):
        assert float(row["arrival_s"]) == pytest.approx(stamps[k], abs=1e-6)
        assert float(row["written_s"]) >= stamps[k]  # the command waited for the stamp
        due = stamps[k + 1] if k + 1 < FRAMES else float("inf")
        assert row["missed"] == str(int(float(row["written_s"]) > due))
    missed = [int(row["frame"]) for row in rows if row["missed"] == "1"]
    record = json.loads((tmp_path / "bag.json").read_text())
    assert record["realtime_stamps"] and record["realtime_hz"] is None
    assert record["missed_deadlines"] == missed
    assert "realtime at the frames' own stamps:" in printed
    np.testing.assert_allclose(_poses(out), world["poses"], atol=1e-9)
    # `vo --correct --realtime` on the layout the recording was written from: the sequence's times.txt.
    assert main(["vo", "--kitti-odometry", str(kitti), "--sequence", "00", "--correct", str(world["run"]),
                 "--realtime", "--out", str(tmp_path / "vo.txt")]) == 0
    arrivals = [float(row["arrival_s"]) for row in _rows(tmp_path / "vo.csv")]
    assert arrivals == pytest.approx(stamps, abs=1e-6)
    capsys.readouterr()  # vo's own lines (its random images fall back to constant velocity)
    assert main(_live_args(world, tmp_path / "r.txt", "--records", world["tmp"] / "records.txt",
                           "--realtime")) == 2
    assert "--realtime without HZ replays a recording (--bag)" in _one_line(capsys.readouterr().err)
    assert not (tmp_path / "r.txt").exists()


@pytest.fixture
def interruptible() -> object:
    """SIGINT raises KeyboardInterrupt in the main thread, as from a terminal (a suite started in the
    background has it ignored)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_live_stream_corrects_each_record_as_it_arrives_and_ctrl_c_ends_it_with_130(
    world: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str], interruptible: object
) -> None:
    """Records sent one at a time through a pipe: frame k's line appears after its record is sent and
    before the next one is; a SIGINT while the command waits for more ends it with 130, every line whole,
    the poses the forced live corrector's."""
    fifo, out = tmp_path / "records", tmp_path / "live.txt"
    os.mkfifo(fifo)
    main_thread, ended = threading.main_thread().ident, threading.Event()
    order: list[tuple[int, int, int]] = []  # (record, lines before it was sent, lines once it was done)

    def feed() -> None:
        with open(fifo, "w") as stream:
            for k, record in enumerate(world["records"][:4]):
                before = _lines_in(out)
                stream.write(record)
                stream.flush()
                _wait_for(lambda k=k: _lines_in(out) > k)
                order.append((k, before, _lines_in(out)))
            assert main_thread is not None
            signal.pthread_kill(main_thread, signal.SIGINT)
            ended.wait(120)  # the pipe stays open: the command ends by the signal, not at its end

    feeder = threading.Thread(target=feed)
    feeder.start()
    try:
        status = main(_live_args(world, out, "--records", fifo, "--force"))
    finally:
        ended.set()
        feeder.join(timeout=60)
    err = capsys.readouterr().err
    assert status == 130, err
    assert order == [(k, k, k + 1) for k in range(4)]
    assert err.splitlines()[-1] == "dpc-jax live: interrupted; nothing half-written"
    assert "interrupted after 4 frames" in err and "Traceback" not in err
    assert len(_rows(tmp_path / "live.csv")) == 4 and not (tmp_path / "live.json").exists()
    reference = _reference(world, force=True, priors=world["poses"], frames=4)
    np.testing.assert_allclose(_poses(out), np.stack([f.pose for f in reference]), atol=1e-9)


def test_a_bad_record_in_a_stream_ends_it_after_the_frames_before_it(
    world: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fifo, out = tmp_path / "records", tmp_path / "live.txt"
    os.mkfifo(fifo)
    bad = world["records"][2].split()
    bad[3] = "2.0"  # the rotation's first entry: no longer a rotation

    def feed() -> None:
        with open(fifo, "w") as stream:
            stream.write("".join(world["records"][:2]) + " ".join(bad) + "\n")

    feeder = threading.Thread(target=feed)
    feeder.start()
    status = main(_live_args(world, out, "--records", fifo))
    feeder.join(timeout=60)
    err = capsys.readouterr().err
    assert status == 1
    line = _one_line(err)
    assert f"{fifo} line 3: the pose is not rigid" in line and "the 2 frames before it are written" in line
    assert len(_poses(out)) == 2


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _records_with(world: dict, name: str, line: int, change: Callable[[list[str]], list[str]]) -> Path:
    """The records file with record ``line`` (from 1) changed by ``change(fields) -> fields``."""
    records = list(world["records"])
    records[line - 1] = " ".join(change(records[line - 1].split())) + "\n"
    path = world["tmp"] / f"records_{name}.txt"
    path.write_text("".join(records))
    return path


def _rescaled(fields: list[str]) -> list[str]:
    return [*fields[:3], *(f"{2 * float(v):.6g}" for v in fields[3:])]


# case: (the options changed, None removing one; exit status; what the one line says)
BAD = {
    "--decision with --no-mean-test": (
        lambda w: {"--decision": "mean-at-judge", "--no-mean-test": ""}, 2,
        ["--decision mean-at-judge says where the correction's mean is tested, --no-mean-test"]),
    "a recording's name as --out": (
        lambda w: {"--out": w["tmp"] / "live.bag"}, 2, ["--out", "live.bag: live writes KITTI pose text"]),
    "a record's image missing": (
        lambda w: {"--records": _records_with(w, "gone", 2, lambda f: [f[0], f[1], f[2] + ".gone", *f[3:]])},
        1, ["line 2: right image", ".gone: no such file"]),
    "a pose that is not rigid": (
        lambda w: {"--records": _records_with(w, "scaled", 3, _rescaled)}, 1,
        ["line 3: the pose is not rigid", "expected a rigid camera-to-world pose"]),
    "a record of 13 fields": (
        lambda w: {"--records": _records_with(w, "short", 1, lambda f: f[:-2])}, 1,
        ["line 1: 13 fields", "expected LEFT RIGHT and the 12 numbers"]),
    "images of another size than the calibration's": (
        lambda w: {"--records": w["tmp"] / "records.txt", "--image-size": "40x64"}, 1,
        ["line 1: left image", "is 48x72, expected 40x64"]),
    "a run larger than the images": (
        lambda w: {"--records": w["tmp"] / "records.txt", "--checkpoint": w["big_run"]}, 2,
        ["takes 64x96 images, larger than the 48x72 images", "never upsampled"]),
    "a calibration without the images' size": (
        lambda w: {"--records": w["tmp"] / "records.txt", "--image-size": None}, 2,
        ["does not give the images' size (a calib.txt has none)", "--image-size HxW"]),
    "a level outside (0, 1)": (lambda w: {"--alpha": "1.5"}, 2, ["--alpha 1.5", "a level in (0, 1)"]),
    "a rate of 0": (lambda w: {"--realtime": "0"}, 2, ["--realtime 0.0", "frames per second (> 0"]),
    "a rate whose waits overflow the clock": (lambda w: {"--realtime": "1e-300"}, 2,
                                              ["--realtime 1e-300", "at least one frame an hour"]),
    "a TIME not after the previous record's": (
        lambda w: {"--records": _records_with(w, "again", 3, lambda f: ["0.1", *f[1:]])}, 1,
        ["line 3: TIME 0.1 is not after line 2's 0.1", "expected increasing times"]),
    "the grey pair's images with the colour pair's calibration": (
        lambda w: {"--records": _records_with(w, "grey", 1, lambda f: [
            f[0], f[1].replace("image_2", "image_0"), f[2].replace("image_3", "image_1"), *f[3:]])}, 1,
        ["line 1: left image", "image_0/000000.png is grey", "holds both pairs", "give --grey"]),
    "a record of TIME LEFT RIGHT and 11 numbers": (
        lambda w: {"--records": _records_with(w, "eleven", 2, lambda f: f[:-1])}, 1,
        ["line 2: 14 fields, TIME LEFT RIGHT and 11 numbers", "expected LEFT RIGHT and the 12 numbers"]),
    "a judge larger than the images": (lambda w: {"--judge-size": "64x96"}, 2,
                                       ["--judge-size 64x96", "larger than the source images (48x72)"]),
    "a judge smaller than the network's images": (lambda w: {"--judge-size": "24x40"}, 2,
                                                  ["--judge-size 24x40", "smaller than the run's images"]),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_is_one_line_before_jax(
    case: str, world: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Each mistake ends in one line naming the record (or option) and what was expected, exit status 1
    for a file's content and 2 for the command line, before JAX would start, with nothing written."""
    import dpc_jax.cli.live as live_cli

    monkeypatch.setattr(live_cli, "import_jax", lambda: pytest.fail("JAX started before the check"))
    make, status, needles = BAD[case]
    args = _live_args(world, tmp_path / "live.txt")
    for option, value in make(world).items():
        if option in args:
            where = args.index(option)
            del args[where:where + 2]
        if value is not None:
            args += [option] if value == "" else [option, str(value)]  # "": a flag
    assert main(args) == status
    line = _one_line(capsys.readouterr().err)
    assert all(needle in line for needle in needles), line
    assert os.listdir(tmp_path) == []


def test_vo_correct_refuses_a_larger_run_and_options_without_it(
    world: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import dpc_jax.cli.vo as vo_cli

    monkeypatch.setattr(vo_cli, "import_jax", lambda: pytest.fail("JAX started before the check"))
    common = ["vo", "--kitti-odometry", str(world["kitti"]), "--sequence", "00",
              "--out", str(tmp_path / "x.txt")]
    assert main([*common, "--correct", str(world["big_run"])]) == 2
    assert "takes 64x96 images, larger than the 48x72 images of 00" in _one_line(capsys.readouterr().err)
    assert main([*common, "--force", "--decision", "mean-at-judge", "--realtime", "10"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert "--force, --decision, --realtime: only used with --correct RUN" in err
    assert main([*common, "--prior-out", str(tmp_path / "p.txt")]) == 2
    assert "--prior-out" in _one_line(capsys.readouterr().err)
    # A recording's name would receive KITTI rows no player opens: refused before anything runs.
    recording = [*common[:-2], "--out", str(tmp_path / "live.mcap")]
    assert main(recording) == 2
    assert "live.mcap: vo writes KITTI pose text, not a recording" in _one_line(capsys.readouterr().err)
    assert os.listdir(tmp_path) == []


def test_files_beside_the_outputs_that_dpc_jax_did_not_write_are_refused_before_any_work(
    world: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The files named after ``--out`` (its CSV and summary, ``vo --correct``'s prior and its record) are
    the command's, not the user's: one of the user's there is refused in one line before JAX, and every
    file is left as it was."""
    import dpc_jax.cli.live as live_cli
    import dpc_jax.cli.vo as vo_cli

    for module in (live_cli, vo_cli):
        monkeypatch.setattr(module, "import_jax", lambda: pytest.fail("JAX started before the check"))
    records = ["--records", world["tmp"] / "records.txt"]
    vo = ["vo", "--kitti-odometry", str(world["kitti"]), "--sequence", "00", "--correct", str(world["run"])]
    cases = {  # the user's file: the command, what the line says
        "a.json": (_live_args(world, tmp_path / "a.txt", *records), "(its .json summary)"),
        "b.csv": (_live_args(world, tmp_path / "b.txt", *records), "(its CSV; --csv names another)"),
        "y.prior.txt": ([*vo, "--out", str(tmp_path / "y.txt")], "the prior's default path"),
        "z.prior.json": ([*vo, "--out", str(tmp_path / "z.txt")], "(its .json record)"),
    }
    for name in cases:
        (tmp_path / name).write_text("the user's\n")
    before = {path.name: path.read_bytes() for path in tmp_path.iterdir()}
    for name, (argv, words) in cases.items():
        assert main(argv) == 2, name
        line = _one_line(capsys.readouterr().err)
        assert f"{tmp_path / name} exists and was not written by dpc-jax" in line and words in line, line
    assert {path.name: path.read_bytes() for path in tmp_path.iterdir()} == before


def test_live_that_corrects_no_frame_leaves_every_file_as_it_was(
    world: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """No records (``< /dev/null``), or a first record that cannot be used in a stream: one line, exit
    status 1, and the outputs are never opened: no empty poses file, no header-only CSV, and the files of
    an earlier run (recorded as its own) untouched."""
    out = tmp_path / "live.txt"
    assert main(_live_args(world, out, "--records", "/dev/null")) == 1
    assert "/dev/null: no records" in _one_line(capsys.readouterr().err)
    assert os.listdir(tmp_path) == []
    assert main(_live_args(world, out, "--records", world["tmp"] / "records.txt", "--force")) == 0
    capsys.readouterr()
    before = {path.name: path.read_bytes() for path in tmp_path.iterdir()}
    assert sorted(before) == [".dpc-jax-files", "live.csv", "live.json", "live.txt"]
    fifo = tmp_path / "records"
    os.mkfifo(fifo)
    feeder = threading.Thread(target=lambda: fifo.write_text("0 gone.png gone.png 1 0 0 0 0 1 0 0 0 0 1 0\n"))
    feeder.start()
    status = main(_live_args(world, out, "--records", fifo))
    feeder.join(timeout=60)
    assert status == 1 and "line 1: left image gone.png: no such file" in _one_line(capsys.readouterr().err)
    fifo.unlink()
    assert {path.name: path.read_bytes() for path in tmp_path.iterdir()} == before
