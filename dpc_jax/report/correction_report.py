"""The report of a corrected sequence (:class:`dpc_jax.results.correction.Correction`): the
acceptance test, how the final correction was chosen, what the adaptation did, and the evaluation
when there is ground truth."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path

from dpc_jax._io import atomic_write
from dpc_jax.report.evaluation_report import write_report
from dpc_jax.report.tables import row, rule
from dpc_jax.results.acceptance import Acceptance, PairedTest
from dpc_jax.results.correction import AdaptationSummary, Correction

_TEST_COLUMNS = ("pairs", "mean Δ", "median Δ", "pairs improved", "Wilcoxon W", "p (one-sided)", "passed")


def rotation_axes_words(component: str) -> str:
    """``rotation_xz`` → ``"rotation about x, z"`` (camera axes)."""
    return "rotation about " + ", ".join(component.removeprefix("rotation_"))


def applied_words(acceptance: Acceptance, rotation_only: bool = False) -> str:
    """What an acceptance test let through, in words: ``none``, ``full 6-DoF``, ``rotation only``,
    ``rotation about x, z only``, each with ``without its mean`` (its moving mean removed; the overall
    mean of what was removed in mm and mrad) and the judge's scale."""
    component = acceptance.component
    if component == "none":
        return "none"
    words = {"full": "rotation only" if rotation_only else "full 6-DoF", "rotation": "rotation only"}.get(
        component) or f"{rotation_axes_words(component)} only"
    if acceptance.remainder and acceptance.mean is not None:
        mean = acceptance.mean
        rotation = ", ".join(f"{1e3 * v:+.3f}" for v in mean[3:])
        translation = ("" if component != "full"
                       else " mm, ".join(f"{1e3 * v:+.2f}" for v in mean[:3]) + " mm; ")
        over = f" over {acceptance.window} pairs" if acceptance.window else ""
        words += f", without its mean{over} (on average {translation}{rotation} mrad per step)"
    if acceptance.scale != 1.0:
        words += f", ×{acceptance.scale:g}"
    return words


def _test_row(t: PairedTest) -> str:
    return _row(t.component, t.pairs, t.mean_delta, t.median_delta, t.improved_share, t.statistic, t.p_value,
                t.passed)


def _row(component: str, pairs: int, mean_delta: float, median_delta: float, improved_share: float,
         statistic: float, p_value: float, passed: bool, std_delta: float = math.nan) -> str:
    return row([component, str(pairs), f"{mean_delta:.3e}", f"{median_delta:.3e}",
                f"{100 * improved_share:.1f} %", f"{statistic:.4g}", f"{p_value:.3g}",
                "yes" if passed else "no"])


def acceptance_markdown(acceptance: Acceptance) -> str:
    """The acceptance test as Markdown: one row per component tested, then the decision."""
    lines = [row(["component", *_TEST_COLUMNS]), rule(1 + len(_TEST_COLUMNS)),
             *(_test_row(t) for t in acceptance.tests.values())]
    applied = applied_words(acceptance)
    applied = "nothing: the corrected trajectory is the prior" if applied == "none" else applied
    return "\n".join([
        *lines, "",
        f"Δ = L(ξ_corr) − L(0) per frame pair: the gradient-masked photometric error of the temporal "
        f"reconstructions with the correction minus without it, same depth (negative: the correction "
        f"explains the images better). \"X − mean\": the correction without its moving mean over "
        f"consecutive pairs; \"mean of X\": Δ(X) − Δ(X − mean), whether the mean helps. Test: one-sided "
        f"Wilcoxon signed-rank at α = {acceptance.alpha:g}.",
        "",
        f"**Applied: {applied}** ({acceptance.reason}).",
        "",
    ])


def choice_markdown(choice: Mapping[str, object]) -> str:
    """How :func:`dpc_jax.correction.corrector.choose` decided, as Markdown (a table row for the
    comparison, if one was made)."""
    lines = ["## Final choice (no ground truth used)", "", f"**{choice['final']}**: {choice['reason']}.", ""]
    comparison = choice.get("comparison")
    if isinstance(comparison, dict):
        lines += [row(["comparison", *_TEST_COLUMNS]), rule(1 + len(_TEST_COLUMNS)), _row(**comparison), ""]
    return "\n".join(lines)


def adaptation_markdown(adaptation: AdaptationSummary) -> str:
    """What the adaptation did, as a Markdown section."""
    a = adaptation
    return (f"## Adaptation (no ground truth used)\n\n{a['steps']} steps on this sequence's own "
            f"pairs in {a['seconds'] / 60:.1f} min; {a['held_out']} pairs kept out for the acceptance "
            f"test (every {a['holdout_every']}th).\n\n")


def write_correction_report(
    directory: str | os.PathLike, correction: Correction, title: str
) -> list[Path]:
    """``report.md`` (acceptance test; with ground truth also the metrics, CSV tables and plots),
    ``summary.json`` and, with ground truth, ``metrics.json`` in ``directory``."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    section = "## Acceptance test (no ground truth used)\n\n" + acceptance_markdown(correction.acceptance)
    if correction.choice is not None:
        section += "\n" + choice_markdown(correction.choice)
    if correction.adaptation is not None:
        section = adaptation_markdown(correction.adaptation) + section
    written: list[Path] = []
    if correction.evaluation is not None:
        written = write_report(directory, correction.evaluation, title)
        report = directory / "report.md"
        atomic_write(report, report.read_text() + "\n" + section)
        atomic_write(directory / "metrics.json", correction.evaluation.to_json())
        written.append(directory / "metrics.json")
    else:
        text = f"# {title}\n\nNo ground truth: nothing to evaluate.\n\n{section}"
        atomic_write(directory / "report.md", text)
        written.append(directory / "report.md")
    atomic_write(directory / "summary.json", json.dumps(correction.to_dict(), indent=2) + "\n")
    return [*written, directory / "summary.json"]
