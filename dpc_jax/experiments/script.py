"""What every experiment script does around its work: claim its outputs, say what goes wrong in one line,
show progress, log with the elapsed time, print its table and put it into its results page."""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from dpc_jax.pipelines.protocol import Named, claim_workdir, path_argument
from dpc_jax.report.pages import check_results_page, read_block, replace_block, write_results
from dpc_jax.report.tables import row, table
from dpc_jax.runtime.progress import Progress, progress_mode

# The environment variable naming the folder of the real data: KITTI raw drives (``kitti-raw/``) and the
# libviso2 estimates (``kitti-libviso2/``); the tests read it from the same variable.
DATA_VARIABLE = "DPC_JAX_DATA"


def data_default(folder: str) -> Path | None:
    """The real data's ``folder`` (``kitti-raw``, ``kitti-libviso2``): in ``$DPC_JAX_DATA`` when it is set,
    else in ``../shared/data`` beside the checkout this package runs from, when it runs from one (an
    editable install); None where that holds no such folder."""
    named = os.environ.get(DATA_VARIABLE)
    if named:
        root = Path(named)
    else:
        checkout = Path(__file__).resolve().parents[2]
        if not (checkout / "pyproject.toml").is_file():  # installed: no checkout, no data beside it
            return None
        root = checkout.parent / "shared" / "data"
    return root / folder if (root / folder).is_dir() else None


def add_data_option(parser: argparse.ArgumentParser, option: str, folder: str, *, metavar: str,
                    help: str) -> None:
    """``option DIR``: the real data's ``folder``, by default :func:`data_default`'s (None when there is
    none: :func:`data_given` refuses it where the script needs it)."""
    found = data_default(folder)
    where = "none found, so give it" if found is None else str(found).replace("%", "%%")
    parser.add_argument(option, type=path_argument, default=found, metavar=metavar,
                        help=f"{help} (default: {folder}/ in ${DATA_VARIABLE}, else in ../shared/data beside "
                        f"the checkout: {where})")


def add_kitti_raw_option(parser: argparse.ArgumentParser) -> None:
    """``--kitti-raw ROOT``: the KITTI raw root (:func:`add_data_option`)."""
    add_data_option(parser, "--kitti-raw", "kitti-raw", metavar="ROOT",
                    help="raw root holding DATE/ and libviso2/")


def data_given(path: Path | None, option: str) -> Path:
    """``path``, the value of a data option (:func:`add_data_option`); ``ValueError`` naming ``option``
    when it was not given and has no default."""
    if path is None:
        raise ValueError(f"{option}: not given, and no default found (in ${DATA_VARIABLE} when it is set, "
                         "else in ../shared/data beside the checkout); pass "
                         f"{option} DIR or set {DATA_VARIABLE}=DIR")
    return path


def new_parser(doc: str | None) -> argparse.ArgumentParser:
    """A script's parser: its docstring (the command and what it writes) as ``--help``'s text, verbatim."""
    return argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)


def add_results_page(parser: argparse.ArgumentParser) -> None:
    """``--results-page FILE``: also write the table into that page's results block."""
    parser.add_argument("--results-page", type=path_argument, metavar="FILE",
                        help="also write the table into the results block of FILE (a docs/results/ page)")


def add_no_progress(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def progress_flag(no_progress: bool) -> Progress:
    """The command line's progress policy (``dpc_jax.runtime.progress.progress_mode``): a bar on a
    terminal, a line every few seconds in a log, nothing with ``--no-progress``."""
    return progress_mode(no_progress)


# The scripts documented to share a work folder (each one's docstring says so): one of a group may write
# into a work folder another of it made. Any other script's work folder is refused (``claim``).
SHARED_WORKDIRS = (frozenset({"kitti_raw_excerpt", "excerpt_ground_truth"}),)


def claim(workdir: str | os.PathLike[str] | None, inputs: Sequence[Named] = (), *,
          script: str | os.PathLike[str], page: Path | None = None, option: str = "--workdir",
          files: Sequence[Named] = ()) -> Path | None:
    """Check the results page (it must have a results block) and claim the work folder and file outputs
    for ``script`` (its path or name; ``dpc_jax.pipelines.protocol.claim_workdir``, the page among them):
    before any work. A work folder another script made is refused unless the two share it
    (:data:`SHARED_WORKDIRS`). Raises ``OSError`` or ``ValueError`` with one line."""
    check_results_page(page)
    owner = Path(script).stem
    shares = sorted({name for group in SHARED_WORKDIRS if owner in group for name in group} - {owner})
    return claim_workdir(workdir, inputs, option=option, files=[*files, ("--results-page", page)],
                         owner=owner, shares=shares)


def refuse(script: str, error: BaseException | str, status: int = 2) -> int:
    """Print ``SCRIPT: error: ...`` (one line, on stderr) and return ``status`` (2: bad input; 1: the work
    failed)."""
    print(f"{script}: error: {error}", file=sys.stderr)
    return status


def interruptible(main: Callable[[], int], script: str | os.PathLike[str]) -> int:
    """``main()``'s exit status, Ctrl-C as the commands end on it: one line on stderr and 130, not a
    traceback (what the script finished is kept: its runs and caches resume when it is run again)."""
    try:
        return main()
    except KeyboardInterrupt:
        print(f"{Path(script).name}: interrupted; what it finished is kept, and the same command resumes",
              file=sys.stderr)
        return 130


def publish(text: str, page: Path | None, script: str | os.PathLike[str]) -> None:
    """Print the table ``text``; with ``page``, also write it into that page's results block, the script
    named as its writer."""
    print(text, end="" if text.endswith("\n") else "\n")
    if page is not None:
        write_results(page, text, Path(script))
        print(f"results page: {page}")


def replace_rows(page: Path, block: str, header: Sequence[str], rows: Sequence[Sequence[str]],
                 run: str) -> None:
    """Put ``rows`` (their first cell: ``run``) into the table of ``page``'s block ``block`` in place of the
    rows of the same run, keeping the other runs' rows (a table that gathers runs of several machines)."""
    kept = [line for line in read_block(page, block).strip().splitlines()[2:]
            if line.startswith("| ") and not line.startswith(row([run]).removesuffix(" |") + " |")]
    replace_block(page, block, table(header, []).rstrip("\n") + "\n" + "\n".join([*kept, *map(row, rows)]))


class Clock:
    """The time since a script started, for its log lines: ``[3.2 min] LINE``."""

    def __init__(self) -> None:
        self.began = time.perf_counter()

    @property
    def minutes(self) -> float:
        return (time.perf_counter() - self.began) / 60

    def say(self, line: str) -> None:
        print(f"[{self.minutes:.1f} min] {line}", flush=True)
