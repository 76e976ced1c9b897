"""A short Markdown report (``report.md``) of a study: the metrics table, the divergence test and the figures."""

from __future__ import annotations

from typing import Any

from .metrics import DIVERGENCE_FRACTION_OF_FREE, DIVERGENCE_GROWTH, FIX_BIN_NAMES
from .scenario import FREE_INERTIAL


def _fmt(x: Any, digits: int = 1, pct: bool = False) -> str:
    if x is None:
        return "–"
    if pct:
        return f"{100.0 * float(x):.0f} %"
    x = float(x)
    if abs(x) >= 1e4:
        return f"{x:.3g}"
    return f"{x:.{digits}f}"


def _pct(x: Any) -> str:
    """A small fraction as a percentage with one decimal ("0.3 %")."""
    return "–" if x is None else f"{100.0 * float(x):.1f} %"


def metrics_table(doc: dict[str, Any]) -> str:
    """Markdown table: one row per estimator, the free-inertial baseline last."""
    head = (
        "| estimator | matcher | fusion | RMS (m) | mean (m) | max (m) | final (m) | diverged | availability "
        "| fixes < 3 m | NEES (2-D) | fix NEES | HPL median (m) | HPL exceeded |\n"
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    rows = []
    entries = list(doc["estimators"].items())
    if doc.get("free_inertial") is not None:
        entries.append((FREE_INERTIAL, doc["free_inertial"]))
    for name, m in entries:
        rows.append(
            f"| {name} | {m.get('matcher') or '–'} | {m.get('fusion')} | {_fmt(m['rms_horizontal_m'])} "
            f"| {_fmt(m['mean_horizontal_m'])} | {_fmt(m['max_horizontal_m'])} | {_fmt(m['final_horizontal_m'])} "
            f"| {_fmt(m['divergence_rate'], pct=True)} | {_fmt(m['availability'], pct=True)} "
            f"| {_fmt(m['fix_within_3m_fraction'], pct=True)} | {_fmt(m['nees_mean'], 2)} "
            f"| {_fmt(m.get('fix_nees_mean'), 2)} | {_fmt(m.get('hpl_median_m'))} "
            f"| {_pct(m.get('hpl_exceedance'))} |"
        )
    return head + "\n".join(rows) + "\n"


def fix_bins_table(doc: dict[str, Any]) -> str:
    """Markdown table of fix error bins (Shockley's < 3, 3-10, 10-20, >= 20 m) per estimator with fixes."""
    lines = ["| estimator | fixes | " + " | ".join(FIX_BIN_NAMES) + " |", "|---|---:|" + "---:|" * len(FIX_BIN_NAMES)]
    for name, m in doc["estimators"].items():
        if not m.get("fixes_issued"):
            continue
        bins = m["fix_error_bins"]
        lines.append(
            f"| {name} | {m['fixes_issued']} | " + " | ".join(_fmt(bins[b], pct=True) for b in FIX_BIN_NAMES) + " |"
        )
    return "\n".join(lines) + "\n" if len(lines) > 2 else ""


def markdown_report(doc: dict[str, Any], figures: list[str] | None = None, command: str | None = None) -> str:
    """The report text for a ``metrics.json`` document ``doc``; ``figures`` are PNG file names beside it."""
    parts = [f"# Study: {doc.get('name') or 'unnamed'}\n"]
    parts.append(f"{doc['runs']} Monte Carlo run(s), seed {doc['seed']}, wall time {doc['wall_s']:.1f} s.\n")
    if command:
        parts.append(f"Reproduce: `{command}`\n")
    parts.append(metrics_table(doc))
    if doc.get("warnings"):
        parts.append("\n**Warnings**\n\n" + "".join(f"- {w}\n" for w in doc["warnings"]))
    fb = fix_bins_table(doc)
    if fb:
        parts.append("\nFix errors (fraction of issued fixes per bin):\n\n" + fb)
    parts.append(
        "\nErrors are horizontal (m), pooled over runs and samples; *final* is the RMS over runs at the last "
        "sample; *availability* = fixes issued / fix attempts; NEES is the horizontal 2-D NEES (2 when "
        "consistent), *fix NEES* the same for the issued fixes against the truth with their own covariances; "
        "*HPL* is the fuser's horizontal protection level (integrity risk 1e-3 per epoch unless the fusion sets "
        "`integrity_risk`), *HPL exceeded* the share of samples where the true error was larger. "
        f"A run *diverges* when its mean error over the last quarter exceeds {DIVERGENCE_GROWTH:g}x "
        f"its mean over the second quarter and {DIVERGENCE_FRACTION_OF_FREE:g}x the free-inertial mean over the "
        "last quarter of the same run (Wang et al. 2022: error growing without apparent bound).\n"
    )
    for f in figures or []:
        parts.append(f"\n![{f}]({f})\n")
    return "\n".join(parts)
