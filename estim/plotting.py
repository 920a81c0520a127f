"""Plots of logs (matplotlib is an optional extra: ``pip install estim[plot]``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def _pyplot():
    try:
        import matplotlib.pyplot as plt  # falls back to Agg without a display
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("plotting needs matplotlib: pip install 'estim[plot]'") from exc
    return plt


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
    axes[-1, 0].set_xlabel("time")
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig


def plot_comparison(result, path=None, seed_index: int = 0):
    """Truth and every estimator's estimate per state for one seed, and RMSE box plots.

    The state axes are limited to the truth's range widened by its span, so a
    wild transient of one estimator does not flatten the others (it leaves
    the axes instead).
    """
    plt = _pyplot()
    if not result.logs:
        raise ValueError("plot_comparison needs the logs: run compare(..., keep_logs=True)")
    names = list(result.logs)
    first = result.logs[names[0]][seed_index]
    nx = first.x.shape[1]
    fig, axes = plt.subplots(nx + 1, 1, figsize=(8, 1.8 * nx + 2.6), squeeze=False)
    axes = axes[:, 0]
    t = first.t
    for j in range(nx):
        ax = axes[j]
        truth = first.x[:, j]
        ax.plot(t, truth, "k-", lw=1.6, label="truth")
        for i, name in enumerate(names):
            ax.plot(t, result.logs[name][seed_index].x_hat[:, j], "-", lw=1.0,
                    color=f"C{i}", label=name)
        lo, hi = float(truth.min()), float(truth.max())
        span = max(hi - lo, 1e-3 * max(abs(lo), abs(hi), 1.0))
        ax.set_ylim(lo - span, hi + span)
        ax.set_ylabel(first.state_names[j] if first.state_names else f"x{j + 1}")
        ax.grid(alpha=0.3)
        if j < nx - 1:
            ax.tick_params(labelbottom=False)
    axes[nx - 1].set_xlabel("time")
    axes[0].legend(loc="upper right", fontsize=8, ncol=min(4, len(names) + 1))
    axes[0].set_title(f"{result.scenario}: seed {result.seeds[seed_index]}")
    box = axes[nx]
    box.boxplot([result.rmse[n] for n in names], tick_labels=names)
    box.set_ylabel(f"RMSE ({len(result.seeds)} seeds)")
    box.set_yscale("log")
    box.grid(alpha=0.3)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig


def plot_estimates(logs, path=None, *, labels=None, styles=None, symlog: float | None = None,
                   title: str | None = None, marker_time: float | None = None):
    """Truth (from the first log) and every log's estimate, one axis per state.

    Parameters
    ----------
    logs : dict of name -> Log
        Runs on the same truth (same scenario and seed).
    path : str or Path, optional
        Write the figure there.
    labels, styles : dict, optional
        Legend label and matplotlib keyword arguments per name.
    symlog : float, optional
        Symmetric-log y axes, linear within ``±symlog`` (large transients and
        small values on one axis).
    title : str, optional
    marker_time : float, optional
        A dotted vertical line (e.g. the end of a burn-in).

    Returns
    -------
    matplotlib.figure.Figure
    """
    plt = _pyplot()
    labels, styles = labels or {}, styles or {}
    truth = next(iter(logs.values()))
    names = truth.state_names or [f"x{i + 1}" for i in range(truth.x.shape[1])]
    fig, axes = plt.subplots(len(names), 1, sharex=True, figsize=(7.5, 2.5 * len(names)),
                             constrained_layout=True, squeeze=False)
    for i, (ax, name) in enumerate(zip(axes[:, 0], names, strict=True)):
        ax.plot(truth.t, truth.x[:, i], color="black", lw=2, label="truth")
        for key, log in logs.items():
            ax.plot(log.t, log.x_hat[:, i], lw=1.2, label=labels.get(key, key),
                    **styles.get(key, {}))
        if symlog is not None:
            ax.axhline(0.0, color="0.6", lw=0.6)
            ax.set_yscale("symlog", linthresh=symlog)
        if marker_time is not None:
            ax.axvline(marker_time, color="0.6", lw=0.6, ls=":")
        ax.set_ylabel(name)
        ax.grid(True, which="major", alpha=0.3)
    axes[0, 0].legend(loc="upper right", ncol=min(4, len(logs) + 1), fontsize="small")
    if title:
        axes[0, 0].set_title(title, fontsize="medium")
    axes[-1, 0].set_xlabel("time")
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig


def plot_errors(logs, path=None, sigma: float = 2.0):
    """Estimation error per state with ``±sigma`` standard-deviation bands where ``P`` exists.

    Parameters
    ----------
    logs : Log or dict of name -> Log
    path : str or Path, optional
    sigma : float
        Width of the band in standard deviations (2: about 95 % for a
        consistent Gaussian estimator).

    Returns
    -------
    matplotlib.figure.Figure
    """
    plt = _pyplot()
    from estim.log import Log

    logs = {getattr(logs, "estimator", "estimate") or "estimate": logs} \
        if isinstance(logs, Log) else dict(logs)
    first = next(iter(logs.values()))
    names = first.state_names or [f"x{i + 1}" for i in range(first.x.shape[1])]
    fig, axes = plt.subplots(len(names), 1, sharex=True, figsize=(7.5, 2.2 * len(names)),
                             constrained_layout=True, squeeze=False)
    for k, (label, log) in enumerate(logs.items()):
        err = log.x_hat - log.x
        for i, ax in enumerate(axes[:, 0]):
            ax.plot(log.t, err[:, i], lw=1.0, color=f"C{k}", label=label)
            sd = np.sqrt(np.maximum(log.P[:, i, i], 0.0)) if "P" in log else None
            if sd is not None and np.isfinite(sd).any():
                ax.fill_between(log.t, -sigma * sd, sigma * sd, color=f"C{k}", alpha=0.15,
                                lw=0)
    for i, ax in enumerate(axes[:, 0]):
        ax.axhline(0.0, color="0.5", lw=0.6)
        ax.set_ylabel(f"error {names[i]}")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", fontsize="small")
    axes[0, 0].set_title(f"estimation error, ±{sigma:g}σ bands where a covariance exists",
                         fontsize="medium")
    axes[-1, 0].set_xlabel("time")
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig


def plot_solve_times(logs, path=None):
    """Wall time of every step, per estimator (log scale).

    Parameters
    ----------
    logs : dict of name -> Log (or name -> list of Log, the first is drawn)
    path : str or Path, optional
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 3.2), constrained_layout=True)
    for k, (label, log) in enumerate(logs.items()):
        log = log[0] if isinstance(log, list) else log
        ax.semilogy(log.t, np.maximum(log.solve_time, 1e-9), ".", ms=2, color=f"C{k}",
                    label=f"{label} (median {np.median(log.solve_time) * 1e3:.3g} ms)")
    ax.set_xlabel("time")
    ax.set_ylabel("solve time per step [s]")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize="small")
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig
