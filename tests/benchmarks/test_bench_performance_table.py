"""benchmarks/performance_table.py: one cheap benchmark in quick mode fills both marked blocks.

Checks the file handling, not figures: the block between the markers is replaced in both files
(the docs' full table with provenance, the library versions among it; the README's short one, of the
rows measured in full only), the text around the markers stays byte for byte, the rows of benchmarks
not run are kept, and a second run replaces rather than appends.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from dpc_jax.runtime.versions import versions_line

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "performance_table.py"
BEGIN, END = "<!-- performance:begin -->", "<!-- performance:end -->"
# A row of a table from before the libraries column: kept, its versions "not recorded".
KEPT = ("| kept row | 1×1 | 1 ms | `python benchmarks/bench_core.py` | some CPU | abc1234 | "
        "2026-01-01 |")
KEPT_NOW = ("| kept row | 1×1 | 1 ms | `python benchmarks/bench_core.py` | some CPU | not recorded | "
            "abc1234 | 2026-01-01 |")


def run(docs: Path, readme: Path) -> None:
    subprocess.run([sys.executable, str(SCRIPT), "--quick", "--only", "bench_data",
                    "--docs", str(docs), "--readme", str(readme)], check=True, capture_output=True)


def between(text: str) -> str:
    return text[text.index(BEGIN) + len(BEGIN):text.index(END)]


def test_quick_run_fills_both_blocks_and_keeps_the_rest(tmp_path: Path) -> None:
    docs, readme = tmp_path / "performance.md", tmp_path / "README.md"
    docs.write_text(f"# before\n{BEGIN}\n{KEPT}\n{END}\nafter\n")
    readme.write_text(f"intro\n{BEGIN}\nold\n{END}\n## next\n")
    run(docs, readme)
    run(docs, readme)

    full, short = docs.read_text(), readme.read_text()
    assert full.startswith(f"# before\n{BEGIN}\n") and full.endswith(f"{END}\nafter\n")
    assert short.startswith(f"intro\n{BEGIN}\n") and short.endswith(f"{END}\n## next\n")
    rows = [line for line in between(full).splitlines() if "bench_data.py" in line]
    assert len(rows) == 1 and rows[0].endswith(", quick |") and "input pipeline" in rows[0]
    assert f"| {versions_line()} |" in rows[0]
    assert KEPT_NOW in between(full)
    # The README shows the kept row, measured in full, and not the quick one.
    assert "old" not in between(short) and "bench_data.py" not in between(short)
    assert "| kept row | 1×1 | 1 ms | `python benchmarks/bench_core.py` |" in between(short)
    assert "on some CPU, commit abc1234, 2026-01-01" in between(short)


def test_the_readme_shows_no_quick_figures(tmp_path: Path) -> None:
    docs, readme = tmp_path / "performance.md", tmp_path / "README.md"
    docs.write_text(f"{BEGIN}\n{END}\n")
    readme.write_text(f"{BEGIN}\nold\n{END}\n")
    run(docs, readme)
    assert "bench_data.py" in between(docs.read_text())
    assert between(readme.read_text()).strip().startswith("No figures measured in full yet")
