r"""What a comparison's table says: the plain-text and HTML tables and the notes.

The notes explain a row that stands out: runs that raised, steps that failed or
were flagged (:func:`row_notes`), an estimator whose NEES says its covariance does
not match its errors, or whose RMSE is several times the best one's
(:func:`notes`). :meth:`Comparison.table <estim.Comparison.table>` and the notebook
view of :class:`~estim.Comparison` are built here.
"""

from __future__ import annotations

import html
import textwrap
from typing import TYPE_CHECKING, Any

import numpy as np

from estim.simulate import FAILED_FRACTION

if TYPE_CHECKING:
    from estim.compare import Comparison, ComparisonRow
    from estim.verdicts import Consistency


def row_notes(row: ComparisonRow) -> list[str]:
    """What went wrong in one estimator's runs, a line each (empty when nothing did)."""
    out: list[str] = []
    if row.errors:
        total = row.runs + len(row.errors)
        seed, message = next(iter(row.errors.items()))
        out.append(f"{row.name}: {len(row.errors)} of {total} runs raised and are left "
                   f"out (seed {seed}: {message})")
    if row.steps and row.failures > FAILED_FRACTION * row.steps:
        out.append(f"{row.name}: {row.failures} of {row.steps} steps failed "
                   f"({100 * row.failures / row.steps:.0f} %): the estimates there are "
                   f"re-anchored, see the logs' status")
    if row.steps and row.flagged > FAILED_FRACTION * row.steps:
        out.append(f"{row.name}: {row.flagged} of {row.steps} steps flagged "
                   f"({100 * row.flagged / row.steps:.0f} %): inexact solves, or NIS/cost "
                   f"beyond the 1e-9 chi-square tail (outliers, or an estimator the data "
                   f"contradict); see the logs' status")
    return out


def notes(result: Comparison) -> list[str]:
    r"""Why a row looks the way it does, a line per estimator that needs one.

    A row gets a note when a run raised, steps failed or were flagged
    (:func:`row_notes`), when it is inconsistent (how far its
    errors are from the :math:`\sigma` it reports: :math:`\sqrt{NEES/n}`
    times), or when its RMSE is more than three times the best row's (with
    its largest error). The estimator's :attr:`~estim.Estimator.caveat` and
    the scenario's remark about its class follow, when there are such.
    """
    finite = [r for r in result.rows if np.isfinite(r.rmse_mean)]
    best = min(finite, key=lambda r: r.rmse_mean) if finite else None
    out: list[str] = []
    explained: dict[str, list[str]] = {}
    for r in result.rows:
        parts = []
        v = r.consistency
        if v is not None and (not v.consistent or v.diverged):
            parts.append(_consistency_note(v))
        if best is not None and r is not best and r.rmse_mean > 3 * best.rmse_mean:
            parts.append(f"RMSE {r.rmse_mean / best.rmse_mean:.0f}× the best "
                         f"({best.name}); after the start-up its largest error is "
                         f"{r.largest_error}")
        if parts and v is not None and v.direction == "pessimistic" and \
                getattr(result, "augmented", None):
            parts.append(f"expected with the parameters {result.augmented} estimated as "
                         f"states: process noise on them in Q, which the plant's constant "
                         f"parameters do not have, widens the reported σ")
        if parts:
            out.append(f"{r.name}: " + "; ".join(parts))
            why = r.caveat or result.remarks.get(r.kind, "")
            if why:
                explained.setdefault(why, []).append(r.name)
        out += row_notes(r)
    out += [f"{', '.join(names)}: {why}" for why, names in explained.items()]
    return out


def _consistency_note(v: Consistency) -> str:
    """The note of an inconsistent row, or of one whose seeds diverged: what the verdict
    (:class:`~estim.verdicts.Consistency`) rests on."""
    ratio = float(np.sqrt(max(v.nees_median, 0.0))) if np.isfinite(v.nees_median) else np.nan
    lo, hi = v.interval
    div = v.p_diverged <= (1 - v.level) / 2
    level_off = not v.interval[0] <= 0.5 <= v.interval[1]
    if v.consistent:
        head = f"consistent at level {v.level:g} although it {v.divergence_text()}"
    else:
        head = "inconsistent: " + "; ".join(
            ([v.direction if not div else ("overconfident" if v.mean_level > 0.5 else
                                           "pessimistic") + " over its steps"]
             if level_off else []) +
            ([f"it {v.divergence_text()} (a consistent estimator, with probability <= "
              f"{v.p_diverged:.2g})"] if div else []))
    return (f"{head}; the median seed's errors are {ratio:.2g}× the σ it reports (NEES/n "
            f"median {v.nees_median:.3g}, mean {v.nees_mean:.3g}); mean chi-square level "
            f"{v.mean_level:.3f} (consistent: 0.5; interval [{lo:.3f}, {hi:.3f}])")


def grade(row: Any) -> str:
    """The consistency column: :meth:`Consistency.grade <estim.verdicts.Consistency.grade>`
    of the row's verdict, ``"-"`` without a covariance."""
    return "-" if row.consistency is None else row.consistency.grade()


def table(result: Comparison) -> str:
    """Plain-text table, with the legend, the notes and how the runs were done."""
    w = max([22] + [len(r.name) + 2 for r in result.rows])
    head = (f"{'estimator':<{w}}{'RMSE mean':>11}{'± std':>9}{'NEES/n':>9}{'cons.':>18}"
            f"{'step med':>11}{'step p90':>11}{'failed':>8}{'flagged':>9}")
    burn = getattr(result, "burn_in", 0)
    lines = [f"{result.scenario}: {len(result.seeds)} seed(s)"
             + (f", RMSE and NEES after the first {burn} samples" if burn else ""),
             head, "-" * len(head)]
    for r in result.rows:
        cons = grade(r)
        lines.append(f"{r.name:<{w}}{r.rmse_mean:>11.4g}{r.rmse_std:>9.2g}"
                     f"{r.nees_mean:>9.3g}{cons:>18}{_fmt_time(r.step_median):>11}"
                     f"{_fmt_time(r.step_p90):>11}{r.failures:>8}{r.flagged:>9}")
    lines += [""] + textwrap.wrap(result.LEGEND, width=len(head))
    remarks = notes(result)
    if remarks:
        lines += ["", "Notes:"]
        for n in remarks:
            lines += textwrap.wrap(n, width=len(head), initial_indent="  ",
                                   subsequent_indent="    ")
    if result.parallel:
        lines += [""] + textwrap.wrap(f"Runs: {result.parallel}", width=len(head))
    if result.batched:
        lines += [""] + textwrap.wrap(f"Batched: {result.batched}", width=len(head))
    return "\n".join(lines)


def html_table(result: Comparison) -> str:
    """The table as HTML (the notebook view)."""
    head = "".join(f"<th>{h}</th>" for h in ("estimator", "RMSE mean", "± std", "NEES/n",
                                             "consistent", "step median", "step p90",
                                             "failed", "flagged"))
    body = "".join(
        f"<tr><td>{html.escape(r.name)}</td><td>{r.rmse_mean:.4g}</td>"
        f"<td>{r.rmse_std:.2g}</td><td>{r.nees_mean:.3g}</td><td>{html.escape(grade(r))}</td>"
        f"<td>{_fmt_time(r.step_median)}</td><td>{_fmt_time(r.step_p90)}</td>"
        f"<td>{r.failures}</td><td>{r.flagged}</td></tr>" for r in result.rows)
    items = "".join(f"<li>{html.escape(n)}</li>" for n in notes(result))
    return (f"<p><b>{result.scenario}</b>: {len(result.seeds)} seed(s)</p>"
            f"<table><tr>{head}</tr>{body}</table>"
            f"<p><small>{html.escape(result.LEGEND)}</small></p>"
            + (f"<p><b>Notes</b></p><ul>{items}</ul>" if items else "")
            + (f"<p><small>Runs: {html.escape(result.parallel)}</small></p>"
               if result.parallel else "")
            + (f"<p><small>Batched: {html.escape(result.batched)}</small></p>"
               if result.batched else ""))


def _fmt_time(seconds: float) -> str:
    """Seconds as ``"12.3 µs"``, ``"4.56 ms"`` or ``"7.89 s"`` (``"-"`` when not finite)."""
    if not np.isfinite(seconds):
        return "-"
    if seconds < 1e-3:
        return f"{seconds * 1e6:.1f} µs"
    if seconds < 1:
        return f"{seconds * 1e3:.2f} ms"
    return f"{seconds:.2f} s"
