"""experiments/studies/paper_scale.py's pure parts: the stand-in's lengths, the measurement of a
process, and the Scale table's block in docs (the stages themselves are the CLI's, tested elsewhere)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from conftest import load_script

SCRIPT = Path(__file__).resolve().parents[1] / "experiments" / "studies" / "paper_scale.py"


@pytest.fixture(scope="module")
def scale():
    return load_script(SCRIPT)


KITTI = {"00": 4541, "01": 1101, "02": 4661, "03": 801, "04": 271, "05": 2761,
         "06": 1101, "07": 1101, "08": 4071, "09": 1591, "10": 1201}


def test_the_stand_in_keeps_kittis_proportions(scale) -> None:
    assert scale.lengths(KITTI, None) == KITTI and sum(KITTI.values()) == 23201
    scaled = scale.lengths(KITTI, 4000)
    assert abs(sum(scaled.values()) - 4000) <= len(KITTI)
    assert scaled["00"] == round(4541 * 4000 / 23201) and scaled["04"] == round(271 * 4000 / 23201)
    assert min(scale.lengths(KITTI, 100).values()) == 8  # every sequence keeps a few pairs


def test_a_process_is_measured_from_outside(scale, tmp_path: Path) -> None:
    """150 MB the process allocates count as anonymous memory; 150 MB of a file it maps and reads
    count in the kernel's peak RSS only (page cache); its CPU time is its own."""
    data = tmp_path / "data.bin"
    data.write_bytes(b"\1" * 150_000_000)
    code = ("import numpy as np, time, sys; a = np.ones(150_000_000 // 8); "
            f"m = np.memmap({str(data)!r}, mode='r'); s = int(m[::4096].sum()); "
            "t = time.process_time(); x = 0\nwhile time.process_time() - t < 0.3: x += 1\n"
            "time.sleep(0.3); print(s, a.sum())")
    measured = scale.measure([sys.executable, "-c", code], tmp_path / "log.txt")
    assert 150 <= measured.peak_anon_mb < 280
    assert measured.peak_rss_mb >= measured.peak_anon_mb + 120
    assert 0.3 <= measured.cpu_s < measured.wall_s
    with pytest.raises(RuntimeError, match=r"exit 3; .*log2\.txt\): boom"):
        scale.measure([sys.executable, "-c", "import sys; print('boom'); sys.exit(3)"], tmp_path / "log2.txt")


def test_the_docs_block_keeps_the_rows_of_other_runs(scale, tmp_path: Path, monkeypatch) -> None:
    docs = tmp_path / "performance.md"
    header = " | ".join(scale.HEADER)
    rule = "|---" * len(scale.HEADER) + "|"
    cells = len(scale.HEADER) - 1
    docs.write_text("intro\n<!-- scale:begin -->\n"
                    f"| {header} |\n{rule}\n"
                    "| GPU, 12000 frames, 240×376 | train" + " | x" * (cells - 1) + " |\n"
                    "| CPU, 1000 frames, 240×376 | train" + " | old" * (cells - 1) + " |\n"
                    "<!-- scale:end -->\noutro\n")
    monkeypatch.setattr(scale, "DOCS", docs)
    new = ["CPU, 1000 frames, 240×376", "train", *["new"] * (cells - 1)]
    scale.write_docs([new], "CPU, 1000 frames, 240×376")
    text = docs.read_text()
    assert text.startswith("intro\n<!-- scale:begin -->\n") and text.endswith("<!-- scale:end -->\noutro\n")
    assert "| GPU, 12000 frames, 240×376 | train | x" in text and "old" not in text
    assert text.count("| CPU, 1000 frames, 240×376 | train | new") == 1
