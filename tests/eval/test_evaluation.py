"""evaluate(), reports, exports and the ``dpc-jax evaluate`` command."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from conftest import DATA
from scipy.spatial.transform import Rotation

from dpc_jax.cli import main
from dpc_jax.data.poses_io import read_kitti_poses, read_mat, read_tum, write_kitti_poses, write_tum
from dpc_jax.eval import reference_metrics as ref
from dpc_jax.eval.evaluation import SUMMARY_KEYS, associate_by_time, evaluate
from dpc_jax.geometry.poses import compose

MAT = DATA / "kitti-libviso2" / "stereo_00.mat"
N = 300


def drive(seed: int, yaw_bias: float = 0.0, stop: slice | None = None) -> np.ndarray:
    """Car-like trajectory, 3 m steps with gentle turns; frames in ``stop`` do not move (static)."""
    rng = np.random.default_rng(seed)
    rel = np.tile(np.eye(4), (N - 1, 1, 1))
    yaw = 0.04 * np.sin(np.arange(N - 1) / 15.0) + yaw_bias + 1e-4 * rng.normal(size=N - 1)
    rel[:, :3, :3] = Rotation.from_rotvec(np.outer(yaw, [0.0, 1.0, 0.0])).as_matrix()
    rel[:, 2, 3] = -3.0
    if stop is not None:
        rel[stop, :3, :3] = np.eye(3)
        rel[stop, 2, 3] = -0.01
    return compose(rel, np.eye(4))


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray]:
    gt = drive(0, stop=slice(100, 140))
    est = drive(1, yaw_bias=0.001, stop=slice(100, 140))
    offset = np.eye(4)
    offset[:3, :3] = Rotation.from_rotvec([0.1, 0.5, -0.2]).as_matrix()
    offset[:3, 3] = [10.0, -4.0, 7.0]
    return gt, offset @ est  # the estimate starts elsewhere: evaluate re-anchors it


def test_evaluate_reanchors_and_matches_reference(pair: tuple[np.ndarray, np.ndarray]) -> None:
    gt, est = pair
    result = evaluate(gt, {"prior": est, "perfect": gt})
    assert list(result) == ["num_poses", "estimates"] and result["num_poses"] == N
    assert list(result["estimates"]["prior"]) == list(SUMMARY_KEYS)
    anchored = gt[0] @ np.linalg.inv(est[0]) @ est
    np.testing.assert_allclose(result.trajectories["prior"], anchored, atol=1e-9)
    prior = result["estimates"]["prior"]
    m_ate = [prior["m_ate_trans_m"], prior["m_ate_rot_deg"]]
    np.testing.assert_allclose(m_ate, ref.m_ate(gt, anchored), rtol=1e-9)
    np.testing.assert_allclose(prior["seg_trans_pct"], ref.segment_errors(gt, anchored)[0], rtol=1e-9)
    np.testing.assert_allclose(prior["ate_m"], ref.ate(gt, anchored), rtol=1e-9)
    assert isinstance(prior["loop_closures"], int)
    perfect = result["estimates"]["perfect"]
    assert perfect["m_ate_trans_m"] < 1e-9 and perfect["seg_trans_pct"] < 1e-9
    assert json.loads(result.to_json()) == dict(result)


def test_precision_is_the_argument_not_the_process_setting(pair: tuple[np.ndarray, np.ndarray]) -> None:
    import jax

    from dpc_jax.eval.evaluation import segment_summary

    gt, est = pair
    anchored = gt[0] @ np.linalg.inv(est[0]) @ est
    reference = ref.segment_errors(gt, anchored)[0]
    with jax.enable_x64(False):  # a process in float32, as JAX starts
        default = evaluate(gt, {"prior": est})["estimates"]["prior"]
        coarse = evaluate(gt, {"prior": est}, precision="float32")["estimates"]["prior"]
        summary = segment_summary(gt, anchored)
    np.testing.assert_allclose(default["seg_trans_pct"], reference, rtol=1e-9)
    np.testing.assert_allclose(summary[0], reference, rtol=1e-9)
    assert coarse["seg_trans_pct"] != default["seg_trans_pct"]
    np.testing.assert_allclose(coarse["seg_trans_pct"], reference, rtol=1e-3)
    with pytest.raises(ValueError, match="precision"):
        evaluate(gt, est, precision="float16")


def test_evaluate_remove_static(pair: tuple[np.ndarray, np.ndarray]) -> None:
    gt, est = pair
    result = evaluate(gt, {"prior": est}, remove_static=True)
    kept = ref.remove_static_frames(est)
    np.testing.assert_array_equal(result.frames, kept)
    assert kept.size < N and result["num_poses"] == kept.size
    np.testing.assert_allclose(result.gt, gt[kept])
    # Re-composed from the relative poses between kept frames, starting at the first kept GT pose.
    expected = [gt[kept[0]]]
    for a, b in itertools.pairwise(kept):
        expected.append(expected[-1] @ np.linalg.inv(np.linalg.inv(est[b]) @ est[a]))
    np.testing.assert_allclose(result.trajectories["prior"], np.stack(expected), atol=1e-8)
    m = result["estimates"]["prior"]
    np.testing.assert_allclose(m["rpe_rot_deg"], ref.rpe(gt[kept], np.stack(expected))[1], rtol=1e-7)


def test_evaluate_bad_input(pair: tuple[np.ndarray, np.ndarray]) -> None:
    gt, est = pair
    with pytest.raises(ValueError, match="has 299 poses but the ground truth has 300"):
        evaluate(gt, {"est": est[:-1]})
    with pytest.raises(ValueError, match="invalid estimate label"):
        evaluate(gt, {"a b": est})
    with pytest.raises(ValueError, match="invalid estimate label 'gt'"):
        evaluate(gt, {"gt": est})
    with pytest.raises(ValueError, match="align must be one of"):
        evaluate(gt, est, align="affine")
    with pytest.raises(ValueError, match="rpe_delta"):
        evaluate(gt, est, rpe_delta=N)
    # An estimate that never moves loses every frame but the last to the static-frame rule.
    static = np.repeat(np.eye(4)[None], 3, axis=0)
    with pytest.raises(ValueError, match=r"removing static frames left 1 pose\(s\)"):
        evaluate(gt[:3], {"still": static}, remove_static=True)


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory, pair: tuple[np.ndarray, np.ndarray]) -> dict[str, Path]:
    gt, est = pair
    root = tmp_path_factory.mktemp("inputs")
    write_kitti_poses(root / "gt.txt", gt)
    write_kitti_poses(root / "prior.txt", est)
    write_tum(root / "other.tum", gt[0] @ np.linalg.inv(est[0]) @ est)
    return {"gt": root / "gt.txt", "prior": root / "prior.txt", "tum": root / "other.tum", "root": root}


def test_cli_json_report_export(
    files: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    pair: tuple[np.ndarray, np.ndarray],
) -> None:
    gt, est = pair
    args = ["evaluate", "--gt", str(files["gt"]), "--est", str(files["prior"]), "--est", str(files["tum"]),
            "--label", "prior", "--label", "tum"]
    assert main([*args, "--json", "-"]) == 0
    printed = json.loads(capsys.readouterr().out)
    expected = evaluate(gt, {"prior": est, "tum": est})  # the files hold 17 significant digits
    assert printed["num_poses"] == expected["num_poses"] == N
    for label in ("prior", "tum"):
        assert printed["estimates"][label] == pytest.approx(expected["estimates"][label], rel=1e-9)

    report, export, out_json = tmp_path / "report", tmp_path / "export", tmp_path / "m.json"
    assert main([*args, "--json", str(out_json), "--report", str(report), "--export", str(export)]) == 0
    assert "| prior |" in capsys.readouterr().out  # the table goes to stdout
    assert json.loads(out_json.read_text()) == printed
    # .dpc-jax-files: the record of the files the command wrote, which a rerun may replace.
    assert sorted(p.name for p in report.iterdir()) == [
        ".dpc-jax-files", "c_ate.png", "metrics.csv", "report.md", "segment_errors.csv", "segment_errors.png",
        "trajectory.png"
    ]
    for png in report.glob("*.png"):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    lines = (report / "metrics.csv").read_text().splitlines()
    assert lines[0] == "label," + ",".join(SUMMARY_KEYS) and lines[1].startswith("prior,")
    assert float(lines[1].split(",")[1]) == pytest.approx(printed["estimates"]["prior"]["m_ate_trans_m"])
    text = (report / "report.md").read_text()
    assert "| tum |" in text and "trajectory.png" in text and "800 m" in text
    assert len((report / "segment_errors.csv").read_text().splitlines()) == 1 + 2 * 8
    np.testing.assert_allclose(read_kitti_poses(export / "gt.kitti.txt"), gt, atol=1e-12)
    times, poses = read_tum(export / "prior.tum.txt")
    np.testing.assert_allclose(times, np.arange(N))
    np.testing.assert_allclose(poses, gt[0] @ np.linalg.inv(est[0]) @ est, atol=1e-9)
    assert sorted(p.name for p in export.iterdir()) == [
        ".dpc-jax-files", "gt.kitti.txt", "gt.tum.txt", "prior.kitti.txt", "prior.tum.txt", "tum.kitti.txt",
        "tum.tum.txt"
    ]


def bad_inputs(files: dict[str, Path]) -> list[tuple[list[str], str]]:
    root = files["root"]
    short = root / "short.txt"
    short.write_text("".join(files["prior"].read_text().splitlines(keepends=True)[:-1]))
    broken = root / "broken.txt"
    rows = files["prior"].read_text().splitlines()
    rows[6] = rows[6] + " 1.0"
    broken.write_text("\n".join(rows) + "\n")
    nan = root / "nan.txt"
    rows = files["prior"].read_text().splitlines()
    rows[9] = " ".join(["nan", *rows[9].split()[1:]])
    nan.write_text("\n".join(rows) + "\n")
    badmat = root / "bad.mat"
    scipy.io.savemat(badmat, {"poses": np.zeros((4, 4, 2))})
    gt = ["--gt", str(files["gt"])]
    return [
        ([*gt, "--est", str(short)], "has 299 poses but the ground truth"),
        ([*gt, "--est", str(broken)], "line 7: expected 12 numbers"),
        ([*gt, "--est", str(nan)], "line 10: non-finite"),
        (["--mat", str(badmat)], "no key 'poses_gt'"),
        ([*gt, "--est", str(files["prior"]), "--format", "tum"], "expected 8 numbers"),
        ([*gt, "--est", str(files["prior"]), "--label", "a", "--label", "b"], "2 --label for 1 --est"),
        ([*gt], "needs at least one --est"),
        (["--mat", str(badmat), "--est", str(files["prior"])], "do not combine"),
        ([*gt, "--est", str(root / "missing.txt")], "missing.txt"),
    ]


def test_cli_bad_input_writes_nothing(
    files: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    for args, needle in bad_inputs(files):
        outputs = ["--json", str(tmp_path / "m.json"), "--report", str(out / "r"), "--export", str(out / "e")]
        assert main(["evaluate", *args, *outputs]) == 2, args
        err = capsys.readouterr().err
        assert needle in err and "Traceback" not in err, (args, err)
        assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_cli_real_sequence_subprocess() -> None:
    """The documented command, as a user runs it (fresh process: import, compile, compute)."""
    done = subprocess.run(
        [sys.executable, "-m", "dpc_jax", "evaluate", "--mat", str(MAT), "--remove-static", "--json", "-"],
        capture_output=True, text=True, check=True, timeout=300,
    )
    printed = json.loads(done.stdout)
    _, est = read_mat(MAT)
    kept = ref.remove_static_frames(est)
    assert printed["num_poses"] == kept.size == 3032
    m = printed["estimates"]["est"]
    assert set(m) == set(SUMMARY_KEYS)
    assert 2.0 < m["seg_trans_pct"] < 3.5 and 0.8 < m["seg_rot_deg_per_100m"] < 2.0  # libviso2-s on 00


def test_evaluate_takes_kitti_rows_names_what_is_not_poses_and_prints_in_one_line(
    pair: tuple[np.ndarray, np.ndarray]
) -> None:
    """One rule for poses, as everywhere (``validate_poses``): ``[N, 4, 4]`` or ``[N, 3, 4]`` on either side,
    the same figures; a path where an array is expected, or another shape, is one ``ValueError`` naming the
    argument; ``repr`` is one line of figures, not the arrays."""
    gt, est = pair
    whole = evaluate(gt, {"p": est})
    assert dict(evaluate(gt[:, :3], {"p": est[:, :3, :]})) == dict(whole)
    with pytest.raises(ValueError, match=r"^estimates\['p'\]: expected poses of shape \[N, 4, 4\] or \[N, 3"):
        evaluate(gt, {"p": est[:, :2]})
    with pytest.raises(ValueError, match=r"^gt: the path 'gt.txt'; expected an array of poses .*read_traj"):
        evaluate("gt.txt", est)
    text = repr(whole)
    m = whole.estimates["p"]
    assert text == (f"Evaluation(300 poses, align='none'; p: m-ATE {m['m_ate_trans_m']:.4g} m, segments "
                    f"{m['seg_trans_pct']:.4g} %)")


def _anchored_m_ate(gt: np.ndarray, est: np.ndarray) -> float:
    """The m-ATE (m) of ``est`` against ``gt``, paired pose by pose, re-anchored on the first pose."""
    return ref.m_ate(gt, gt[0] @ np.linalg.inv(est[0]) @ est)[0]


def test_associate_by_time_keeps_the_poses_every_estimate_pairs() -> None:
    """Another rate, dropped frames and a second clock, against the indices they must give."""
    times = 50.0 + 0.1 * np.arange(40)
    dropped = np.delete(np.arange(40), [3, 4, 5, 6, 7])
    a = associate_by_time(times, {"half": times[::2], "dropped": times[dropped] + 0.003})
    np.testing.assert_array_equal(a.gt_indices, np.arange(0, 40, 2)[np.isin(np.arange(0, 40, 2), dropped)])
    np.testing.assert_array_equal(a.indices["half"], a.gt_indices // 2)
    np.testing.assert_array_equal(dropped[a.indices["dropped"]], a.gt_indices)
    assert a.matched == {"half": 20, "dropped": 35} and a.possible == {"half": 20, "dropped": 35}
    shifted = associate_by_time(times, {"late": times + 100.0}, offset=-100.0)
    np.testing.assert_array_equal(shifted.indices["late"], np.arange(40))
    with pytest.raises(ValueError, match=r"^--est x\.tum: 0 of its 40 poses have a ground-truth time within "
                                         r"0\.01 s \(time offset 0 s\); fewer than half match"):
        associate_by_time(times, {"late": times + 100.0}, sources={"late": "--est x.tum"})
    with pytest.raises(ValueError, match="fewer than half"):  # 19 of 40 within 0.01 s
        associate_by_time(times, {"partly": np.concatenate([times[:19], times[19:] + 0.05])})


def test_cli_pairs_timed_trajectories_by_time(
    pair: tuple[np.ndarray, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """TUM files are paired by time as evo does: estimate times shifted by 100 s are refused (and paired
    with --t-offset), 5 dropped frames are paired with the poses of the same times and the summary says
    how many matched. Paired by index, as before, both exited 0 with other numbers."""
    n = 120  # 360 m: every segment length up to 300 m
    gt, est = pair[0][:n], pair[1][:n]
    times = 1.0e9 + 0.1 * np.arange(n)
    write_tum(tmp_path / "gt.tum", gt, times)
    keep = np.delete(np.arange(n), [50, 51, 52, 53, 54])
    variants = {"shifted": (est, times + 100.0), "dropped": (est[keep], times[keep]), "same": (est, times)}
    for name, (poses, stamps) in variants.items():
        write_tum(tmp_path / f"{name}.tum", poses, stamps)

    def run(name: str, *extra: str) -> dict:
        assert main(["evaluate", "--gt", str(tmp_path / "gt.tum"), "--est", str(tmp_path / f"{name}.tum"),
                     "--json", "-", *extra]) == 0
        return json.loads(capsys.readouterr().out)

    assert main(["evaluate", "--gt", str(tmp_path / "gt.tum"), "--est", str(tmp_path / "shifted.tum")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"--est {tmp_path / 'shifted.tum'}: 0 of its 120 poses" in err, err
    same = run("same")["estimates"]["same"]["m_ate_trans_m"]
    assert same == pytest.approx(_anchored_m_ate(gt, est), rel=1e-9)
    assert run("shifted", "--t-offset", "-100")["estimates"]["shifted"]["m_ate_trans_m"] == pytest.approx(
        same, rel=1e-12)
    dropped = run("dropped")
    assert dropped["num_poses"] == keep.size and dropped["association"]["matched"] == {"dropped": keep.size}
    m_ate = dropped["estimates"]["dropped"]["m_ate_trans_m"]
    assert m_ate == pytest.approx(_anchored_m_ate(gt[keep], est[keep]), rel=1e-9)
    assert abs(m_ate - _anchored_m_ate(gt[: keep.size], est[keep])) > 1.0  # what pairing by index gave
    assert main(["evaluate", "--gt", str(tmp_path / "gt.tum"), "--est", str(tmp_path / "dropped.tum")]) == 0
    assert "matched: dropped 115 of 115" in capsys.readouterr().out
    write_kitti_poses(tmp_path / "gt.txt", gt)
    assert main(["evaluate", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "same.tum"),
                 "--t-max-diff", "0.02"]) == 2
    assert "--t-max-diff 0.02: pairing by time needs times in every file" in capsys.readouterr().err
