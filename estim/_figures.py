"""The matplotlib basics of estim's figures, and the figure of one log.

:meth:`Log.plot <estim.Log.plot>` draws with :func:`plot_log`, so it lives below the
log; :mod:`estim.plotting` builds its comparisons on the same pieces (matplotlib is an
optional extra: ``pip install estim[plot]``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def _pyplot():
    try:
        import matplotlib.pyplot as plt  # falls back to Agg without a display
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("plotting needs matplotlib: pip install 'estim[plot]'") from exc
    return plt


#: Line styles cycled with the colours, so overlapping estimates stay distinguishable
#: (a dashed line over a solid one shows both).
_LINESTYLES = ("-", "--", "-.", ":")


#: Backends that draw nothing on screen: a figure there is shown by its PNG in Jupyter.
_NON_INTERACTIVE = ("agg", "cairo", "pdf", "pgf", "ps", "svg", "template")


class _DisplayOnce:
    """``Figure._ipython_display_`` of estim's figures: drawn once in Jupyter.

    A pyplot figure returned as a cell's value is drawn twice there: as the value,
    and by the inline backend when the cell ends. This draws the PNG and, under
    the inline backend, releases the figure from pyplot so that it is not drawn
    again; under a widget or notebook backend, which shows the live figure
    itself, it draws nothing.
    """

    def __init__(self, fig):
        self.fig = fig

    def __call__(self) -> None:
        import io

        import matplotlib
        import matplotlib.pyplot as plt
        from IPython.display import Image, display

        backend = matplotlib.get_backend().lower()
        number = getattr(self.fig, "number", None)
        managed = number is not None and plt.fignum_exists(number)
        inline = "inline" in backend
        if managed and not inline and backend not in _NON_INTERACTIVE:
            return
        buf = io.BytesIO()
        self.fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
        display(Image(data=buf.getvalue()))
        if managed and inline:
            plt.close(self.fig)


def _finish(fig, path):
    """Write the figure if asked, make Jupyter draw it once, and return it."""
    if path is not None:
        fig.savefig(path, dpi=120)
    fig._ipython_display_ = _DisplayOnce(fig)
    return fig


def _style(k: int) -> dict:
    """Colour and line style of the k-th estimator of a figure."""
    return {"color": f"C{k}", "ls": _LINESTYLES[k % len(_LINESTYLES)],
            "lw": 1.6 if k % len(_LINESTYLES) == 0 else 1.3}


def _time_label(log) -> str:
    """``"time [s]"`` from the log's unit; says so when the unit is not known."""
    unit = getattr(log, "time_unit", "") or ""
    if unit == "dimensionless":
        return "time (dimensionless)"
    if unit:
        return f"time [{unit}]"
    dt = getattr(log, "dt", None)
    return "time (unit not given" + (f"; sample time {dt:g})" if dt else ")")


def _settled_limit(values: list[np.ndarray]) -> float:
    """Half-height of an error axis: what the estimators' errors (and bands) settle to.

    ``values`` holds each estimator's absolute errors (and band widths) after the
    start-up transient. Each contributes its 98th percentile; an estimator more than
    ten times the median of the others does not set the scale (it leaves the axis,
    and the figure says so). Returns 0 when there is nothing finite.
    """
    scales = []
    for v in values:
        v = v[np.isfinite(v)]
        if v.size:
            scales.append(float(np.percentile(v, 98)))
    if not scales:
        return 0.0
    med = float(np.median(scales))
    kept = [s for s in scales if s <= 10 * med] or scales
    return 1.3 * max(kept)


def plot_log(log, path=None, states: Sequence[str] | None = None, sigma: bool = True):
    """Draw truth, estimate (± 2σ) and direct measurements per state; see :meth:`Log.plot`."""
    plt = _pyplot()
    names = log.state_names or [f"x{i + 1}" for i in range(log.x_hat.shape[1])]
    idx = list(range(len(names))) if states is None else [names.index(s) for s in states]
    t = log.t if "t" in log else np.arange(len(log))
    fig, axes = plt.subplots(len(idx), 1, sharex=True, figsize=(8, 1.9 * len(idx) + 0.6),
                             squeeze=False)
    measured = {j: i for i, j in log.output_state.items()}
    for ax, j in zip(axes[:, 0], idx, strict=True):
        if j in measured and "y" in log:
            ax.plot(t, log.y[:, measured[j]], ".", ms=2, color="0.6", label="measurement")
        if "x" in log:
            ax.plot(t, log.x[:, j], "k-", lw=1.2, label="truth")
        ax.plot(t, log.x_hat[:, j], "-", lw=1.2, color="C0",
                label=f"estimate ({log.estimator})" if log.estimator else "estimate")
        if sigma and "P" in log and np.isfinite(log.P[:, j, j]).any():
            sd = np.sqrt(np.maximum(log.P[:, j, j], 0.0))
            ax.fill_between(t, log.x_hat[:, j] - 2 * sd, log.x_hat[:, j] + 2 * sd,
                            color="C0", alpha=0.15, lw=0, label="±2σ")
        ax.set_ylabel(names[j])
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[-1, 0].set_xlabel(_time_label(log))
    fig.tight_layout()
    return _finish(fig, path)
