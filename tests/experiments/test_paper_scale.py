"""experiments/studies/paper_scale.py's pure parts (``dpc_jax.experiments.scale``): the stand-in's lengths,
and the Scale table's block in docs, whose rows of other runs stay (the stages themselves are the CLI's,
tested elsewhere; their measurement: test_experiment_kit.py)."""

from __future__ import annotations

from pathlib import Path

from dpc_jax.experiments.scale import HEADER, lengths
from dpc_jax.experiments.script import replace_rows

KITTI = {"00": 4541, "01": 1101, "02": 4661, "03": 801, "04": 271, "05": 2761,
         "06": 1101, "07": 1101, "08": 4071, "09": 1591, "10": 1201}


def test_the_stand_in_keeps_kittis_proportions() -> None:
    assert lengths(KITTI, None) == KITTI and sum(KITTI.values()) == 23201
    scaled = lengths(KITTI, 4000)
    assert abs(sum(scaled.values()) - 4000) <= len(KITTI)
    assert scaled["00"] == round(4541 * 4000 / 23201) and scaled["04"] == round(271 * 4000 / 23201)
    assert min(lengths(KITTI, 100).values()) == 8  # every sequence keeps a few pairs


def test_the_docs_block_keeps_the_rows_of_other_runs(tmp_path: Path) -> None:
    docs = tmp_path / "performance.md"
    header = " | ".join(HEADER)
    rule = "|---" * len(HEADER) + "|"
    cells = len(HEADER) - 1
    docs.write_text("intro\n<!-- scale:begin -->\n"
                    f"| {header} |\n{rule}\n"
                    "| GPU, 12000 frames, 240×376 | train" + " | x" * (cells - 1) + " |\n"
                    "| CPU, 1000 frames, 240×376 | train" + " | old" * (cells - 1) + " |\n"
                    "<!-- scale:end -->\noutro\n")
    new = ["CPU, 1000 frames, 240×376", "train", *["new"] * (cells - 1)]
    replace_rows(docs, "scale", HEADER, [new], "CPU, 1000 frames, 240×376")
    text = docs.read_text()
    assert text.startswith("intro\n<!-- scale:begin -->\n") and text.endswith("<!-- scale:end -->\noutro\n")
    assert "| GPU, 12000 frames, 240×376 | train | x" in text and "old" not in text
    assert text.count("| CPU, 1000 frames, 240×376 | train | new") == 1
