"""Options that cannot take effect, and inputs that do not fit the run or each other, are refused in one
line naming the option and the file, before JAX is imported and before anything is written (issue 40:
Why 5, 7 and 8). All the command lines run in one fresh interpreter, which must not import JAX."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from support import in_one_process, write_odometry

from dpc_jax.data.cache import prepare_sequence
from dpc_jax.data.kitti import open_odometry
from dpc_jax.data.poses_io import write_kitti_poses
from dpc_jax.data.sequence_cache import file_record

SIZE = (10, 16)
N_FRAMES = 6  # forward pairs 5 + skip pairs 4: 9 training samples of one sequence


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two 6-frame odometry sequences, their priors, caches at SIZE (00, 05) and at twice SIZE (00), and
    run folders (a config.json is all the commands read before JAX): Stereo DPC and ss-DPC-Net at SIZE."""
    root = tmp_path_factory.mktemp("inputs")
    for name, seed in (("00", 0), ("05", 1)):
        written = write_odometry(root / "kitti", name=name, n=N_FRAMES, size=(40, 64), seed=seed)
        write_kitti_poses(root / f"prior_{name}.txt", written["poses"])
        sequence = open_odometry(root / "kitti", name)
        prepare_sequence(sequence, root / f"prior_{name}.txt", root / "cache", size=SIZE, progress=False,
                         workers=1)
    prepare_sequence(open_odometry(root / "kitti", "00"), root / "prior_00.txt", root / "cache_large",
                     size=(2 * SIZE[0], 2 * SIZE[1]), progress=False, workers=1)
    write_kitti_poses(root / "short.txt", written["poses"][:3])
    for run, method in (("stereo_run", "stereo_dpc"), ("ss_run", "ss_dpc")):
        (root / run / "checkpoints").mkdir(parents=True)
        config = {"method": method, "validation_sequences": ["05"], "image_size": list(SIZE)}
        (root / run / "checkpoints" / "config.json").write_text(json.dumps(config) + "\n")
    return {"root": root, "kitti": root / "kitti", "cache": root / "cache", "large": root / "cache_large",
            "short": root / "short.txt", "stereo_run": root / "stereo_run", "ss_run": root / "ss_run"}


def _config(path: Path, cache_root: Path, **fields: object) -> Path:
    config = {"method": "stereo_dpc", "preset": "small", "image_size": SIZE, "batch_size": 2, "epochs": 1,
              "pose_warmup_epochs": 0, "cache_root": str(cache_root), "validation_sequences": ("05",),
              **fields}
    path.write_text(f"CONFIG = {config!r}\n")
    return path


def test_options_that_cannot_take_effect_are_refused_before_jax(
    inputs: dict[str, Path], tmp_path: Path
) -> None:
    out, cache = tmp_path / "out", inputs["cache"]
    plain = _config(tmp_path / "plain.py", cache)
    distributed = _config(tmp_path / "distributed.py", cache, distributed=True)
    too_big = _config(tmp_path / "too_big.py", cache, batch_size=10)
    other_size = _config(tmp_path / "other_size.py", cache, image_size=(2 * SIZE[0], 2 * SIZE[1]))
    for name, field in (("method", '"method": "stereo-dpc"'), ("dropout", '"dropout": 1.5')):
        (tmp_path / f"{name}.py").write_text(f'CONFIG = {{{field}, "validation_sequences": ("05",)}}\n')
    repeated = tmp_path / "repeated" / "00"  # a cache whose frame 3 has frame 2's time
    shutil.copytree(cache / "00", repeated)
    times = np.load(repeated / "times.npy")
    times[3] = times[2]
    np.save(repeated / "times.npy", times)
    manifest = json.loads((repeated / "manifest.json").read_text())  # the cache as written with these times
    manifest["arrays"]["times.npy"] = file_record(repeated / "times.npy")
    (repeated / "manifest.json").write_text(json.dumps(manifest))
    existing = tmp_path / "existing"
    (existing / "checkpoints").mkdir(parents=True)
    shutil.copy(inputs["stereo_run"] / "checkpoints" / "config.json", existing / "checkpoints")
    train = ["train", "--config", plain, "--workdir", out / "run"]
    correct = ["correct", "--checkpoint", inputs["stereo_run"], "--data", cache / "00",
               "--out", out / "c.txt"]
    ss_correct = ["correct", "--checkpoint", inputs["ss_run"], "--out", out / "c.txt"]
    prepare = ["prepare", "--kitti-odometry", inputs["kitti"], "--out", out / "cache", "--size", "10x16",
               "--no-progress"]
    cases = {
        # train (Why 5, 7, 8)
        "--coordinator-address, --num-processes, --process-id: multi-host flags, but {t}/plain.py does not "
        "set distributed=True": [*train, "--coordinator-address", "127.0.0.1:1234", "--num-processes", "2",
                                 "--process-id", "5"],
        "--num-processes: multi-host flags, but": [*train, "--num-processes", "2"],
        "--coordinator-address 'no-port': expected HOST:PORT": [
            "train", "--config", distributed, "--workdir", out / "run", "--coordinator-address", "no-port"],
        "--process-id 5: expected 0 to 1 for --num-processes 2": [
            "train", "--config", distributed, "--workdir", out / "run", "--coordinator-address", "h:1234",
            "--num-processes", "2", "--process-id", "5"],
        "--resume: {o}/run holds no training run to continue": [*train, "--resume"],
        "--workers -1: expected 0": [*train, "--workers", "-1"],
        "{t}/existing already holds a training run": ["train", "--config", plain, "--workdir", existing],
        "too_big.py: batch_size 10 is more than the 9 training samples of": [
            "train", "--config", too_big, "--workdir", out / "run"],
        "{c}/00: images are 10x16, but {t}/other_size.py asks for image_size 20x32": [
            "train", "--config", other_size, "--workdir", out / "run"],
        "{t}/method.py: invalid TrainConfig: method must be one of": [
            "train", "--config", tmp_path / "method.py", "--workdir", out / "run"],
        "{t}/dropout.py: ": ["train", "--config", tmp_path / "dropout.py", "--workdir", out / "run"],
        # correct (Why 5, 7, 8)
        "--holdout-every 7: only used with --adapt STEPS": [*correct, "--holdout-every", "7"],
        "--adapt-lr 0.5: only used with --adapt STEPS": [*correct, "--adapt-lr", "0.5"],
        "--decision mean-at-judge says where the correction's mean is tested, --no-mean-test that": [
            *correct, "--decision", "mean-at-judge", "--no-mean-test"],
        "--data {l}/00: images are 20x32, but the run": [
            "correct", "--checkpoint", inputs["stereo_run"], "--data", inputs["large"] / "00",
            "--out", out / "c.txt"],
        "--judge {c}/05: holds frames other than those of --data {c}/00": [*correct, "--judge", cache / "05"],
        "--prior {s}: 3 prior poses for the sequence in {c}/00; expected 6": [*correct, "--prior",
                                                                               inputs["short"]],
        "--acceptance-depth sgbm: StereoSGBM depth needs a stereo run": [
            *ss_correct, "--data", cache / "00", "--acceptance-depth", "sgbm"],
        "--judge-size 20x32: a judge measures Δ with stereo depth (stereo_dpc)": [
            *ss_correct, "--kitti-odometry", inputs["kitti"], "--sequence", "00", "--prior",
            inputs["root"] / "prior_00.txt", "--judge-size", "20x32"],
        "--data {c}/00: no forward flow in the cache, which the network of": [*ss_correct, "--data",
                                                                              cache / "00"],
        "--format tum: the frame times of --data {t}/repeated/00 do not increase at cached frame 3": [
            "correct", "--checkpoint", inputs["stereo_run"], "--data", repeated, "--out", out / "c.tum",
            "--format", "tum"],
        # prepare, vo, synth (Why 7, 8, 9)
        "05: {r}/05.txt: 3 prior poses for 6 frames": [*prepare, "--sequence", "00", "05", "--prior",
                                                inputs["root"] / "{seq}.txt"],
        "3 prior poses for 6 frames; expected one pose per frame, or one per frame of the range 0:4": [
            *prepare, "--sequence", "00", "--frames", "0:4", "--prior", inputs["short"]],
        "--disparity-offset 1e+06: the images of 00 are 64 px wide": [
            *prepare, "--sequence", "00", "--prior", inputs["root"] / "prior_00.txt",
            "--disparity-offset", "1e6"],
        "vo: error: --disparity-offset 1e+06: the images of 00 are 64 px wide": [
            "vo", "--kitti-odometry", inputs["kitti"], "--sequence", "00", "--out", out / "vo.txt",
            "--disparity-offset", "1e6"],
        "vo: error: --judge-size 20x32: a judge measures Δ with stereo depth (stereo_dpc); --correct "
        "{r}/ss_run is ss_dpc": [  # correct's judge policy
            "vo", "--kitti-odometry", inputs["kitti"], "--sequence", "00", "--out", out / "vo.txt",
            "--correct", inputs["ss_run"], "--judge-size", "20x32"],
        "--seed must be >= 0, got -5": ["synth", "--out", out / "s", "--seed", "-5"],
        "--noise must be >= 0, got -1.0": ["synth", "--out", out / "s", "--noise", "-1"],
    }
    # The second sequence's prior is the short one: 00 must not be built before 05 is refused.
    shutil.copy(inputs["root"] / "prior_00.txt", inputs["root"] / "00.txt")
    shutil.copy(inputs["short"], inputs["root"] / "05.txt")
    status, imported, done = in_one_process(list(cases.values()))
    lines = done.stderr.splitlines()
    assert len(lines) == len(cases) and "Traceback" not in done.stderr, done.stderr
    for needle, line in zip(cases, lines, strict=True):
        text = needle.format(o=out, t=tmp_path, c=cache, l=inputs["large"], s=inputs["short"],
                             r=inputs["root"])
        assert text in line, (text, line)
    # prepare and vo report what the files hold with status 1, as for any input they cannot read.
    expected = [1 if argv[0] == "prepare" and "--prior" in map(str, argv) and "--disparity-offset" not in
                map(str, argv) else 2 for argv in cases.values()]
    assert imported == [] and status == expected, (status, imported)
    assert not out.exists()
