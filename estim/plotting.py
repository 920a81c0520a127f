"""Plots of logs and of results of whole records (matplotlib is an optional extra:
``pip install estim[plot]``).

Every function that draws estimates takes :class:`~estim.Log` objects and the results of
``filter``, ``smooth`` and ``fit`` (any :class:`~estim.estimators.filtering.Estimates`)
alike, the latter with the truth given as ``truth=`` (a log of the same record or the
true states) where the figure shows it.
"""

from __future__ import annotations

import numpy as np

from estim._figures import (  # noqa: F401 - plot_log is a name of this module
    _finish,
    _pyplot,
    _settled_limit,
    _style,
    _time_label,
    plot_log,
)
from estim.estimators.filtering import Estimates
from estim.log import Log
from estim.metrics import rmse, startup_samples

#: what the figures of estimates take, for messages
_ACCEPTED = ("an estim.Log, a result of a whole record (FilterResult, SmoothResult, "
             "ParticleFilterResult, ParticleSmoothResult, FitResult) or a dict of them "
             "by label")


def _as_logs(logs, truth, what: str, need_truth: bool) -> tuple[dict[str, Log], Log | None]:
    """The runs as logs by label, and the log whose ``x`` is the truth (None if none).

    ``truth`` (a Log or ``(T, nx)`` array) is given to every result; without it, the
    truth of the first log that has one."""
    if isinstance(logs, (Log, Estimates)):
        name = (logs.estimator if isinstance(logs, Log) else "") or \
            ("estimate" if isinstance(logs, Log) else type(logs).__name__)
        logs = {name: logs}
    if not isinstance(logs, dict) or not logs:
        raise TypeError(f"{what} takes {_ACCEPTED}, got "
                        f"{type(logs).__name__ if not isinstance(logs, dict) else 'an empty dict'}")
    source = truth if isinstance(truth, Log) else next(
        (v for v in logs.values() if isinstance(v, Log) and "x" in v), None)
    given = truth if truth is not None else source
    out: dict[str, Log] = {}
    for key, value in logs.items():
        if isinstance(value, Log):
            if need_truth and "x" not in value:
                raise ValueError(f"{what}: the log {key!r} has no truth 'x' (it has "
                                 f"{value.keys()})")
            out[str(key)] = value
        elif isinstance(value, Estimates):
            if need_truth and given is None:
                raise ValueError(f"{what} needs the truth of {key!r} "
                                 f"({type(value).__name__}): pass truth= a Log of the "
                                 f"same record or the true states (T, nx)")
            out[str(key)] = Log.from_estimates(value, given, name=str(key))
        else:
            raise TypeError(f"{what} takes {_ACCEPTED}; {key!r} is a "
                            f"{type(value).__name__}")
    truth_log = next((v for v in out.values() if "x" in v), None)
    return out, truth_log


def plot_comparison(result, path=None, seed_index: int = 0):
    """Truth and every estimator's estimate per state for one seed, and RMSE box plots.

    The state axes are limited to the truth's range widened by its span, so a
    wild transient of one estimator does not flatten the others (it leaves
    the axes instead). Lines differ in colour and style; the known caveat of
    an estimator's configuration (:attr:`~estim.Estimator.caveat`, e.g. a
    clipped filter) is written under the figure.

    Parameters
    ----------
    result : Comparison
        From ``compare(..., keep_logs=True)``.
    path : str or Path, optional
        Write the figure there.
    seed_index : int
        Which seed to draw, as an index into ``result.seeds``.

    Returns
    -------
    matplotlib.figure.Figure
    """
    plt = _pyplot()
    if not result.logs:
        raise ValueError("plot_comparison needs the logs: run compare(..., keep_logs=True)")
    names = list(result.logs)
    first = next((logs[seed_index] for logs in result.logs.values()
                  if logs[seed_index] is not None), None)
    if first is None:
        raise ValueError(f"no run of seed {result.seeds[seed_index]} kept a log")
    nx = first.x.shape[1]
    fig, axes = plt.subplots(nx + 1, 1, figsize=(8, 1.8 * nx + 2.6), squeeze=False)
    axes = axes[:, 0]
    t = first.t
    for j in range(nx):
        ax = axes[j]
        truth = first.x[:, j]
        ax.plot(t, truth, "k-", lw=1.6, label="truth")
        for i, name in enumerate(names):
            log = result.logs[name][seed_index]
            if log is not None:
                ax.plot(log.t, log.x_hat[:, j], label=name, **_style(i))
        lo, hi = float(truth.min()), float(truth.max())
        span = max(hi - lo, 1e-3 * max(abs(lo), abs(hi), 1.0))
        ax.set_ylim(lo - span, hi + span)
        ax.set_ylabel(first.state_names[j] if first.state_names else f"x{j + 1}")
        ax.grid(alpha=0.3)
        if j < nx - 1:
            ax.tick_params(labelbottom=False)
    axes[nx - 1].set_xlabel(_time_label(first))
    axes[0].legend(loc="upper right", fontsize=8, ncol=min(4, len(names) + 1))
    axes[0].set_title(f"{result.scenario}: seed {result.seeds[seed_index]}")
    box = axes[nx]
    box.boxplot([np.asarray(result.rmse[n])[np.isfinite(result.rmse[n])] for n in names],
                tick_labels=names)
    box.set_ylabel(f"RMSE ({len(result.seeds)} seeds)")
    box.set_yscale("log")
    box.grid(alpha=0.3)
    caveats = [f"{r.name}: {r.caveat}" for r in getattr(result, "rows", []) if r.caveat]
    if caveats:
        # the explanation of a configuration's known behaviour goes where it is seen
        import textwrap

        text = "\n".join(textwrap.fill(c, 125) for c in caveats)
        lines = text.count("\n") + 1
        height = fig.get_figheight() + 0.16 * lines + 0.1
        fig.set_figheight(height)
        fig.text(0.01, 0.01, text, fontsize=7, color="0.25", va="bottom", ha="left")
        fig.tight_layout(rect=(0, (0.16 * lines + 0.15) / height, 1, 1))
    else:
        fig.tight_layout()
    return _finish(fig, path)


def plot_estimates(logs, path=None, *, truth=None, labels=None, styles=None,
                   symlog: float | None = None, title: str | None = None,
                   marker_time: float | None = None):
    """Truth and every run's estimate, one axis per state.

    Parameters
    ----------
    logs : Log, result, or dict of name -> Log or result
        Runs on the same record (same scenario and seed): logs of
        :func:`~estim.simulate` / :func:`~estim.replay` and results of ``filter``,
        ``smooth`` and ``fit``.
    path : str or Path, optional
        Write the figure there.
    truth : Log or (T, nx) array, optional
        The true states (default: those of the first log that has them; none drawn
        when no run has them).
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
    logs, truth_log = _as_logs(logs, truth, "plot_estimates", need_truth=False)
    first = next(iter(logs.values()))
    names = first.state_names or [f"x{i + 1}" for i in range(first.x_hat.shape[1])]
    fig, axes = plt.subplots(len(names), 1, sharex=True, figsize=(7.5, 2.5 * len(names)),
                             constrained_layout=True, squeeze=False)
    for i, (ax, name) in enumerate(zip(axes[:, 0], names, strict=True)):
        if truth_log is not None:
            ax.plot(truth_log.t, truth_log.x[:, i], color="black", lw=2, label="truth")
        for k, (key, log) in enumerate(logs.items()):
            ax.plot(log.t, log.x_hat[:, i], label=labels.get(key, key),
                    **{**_style(k), **styles.get(key, {})})
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
    axes[-1, 0].set_xlabel(_time_label(first))
    return _finish(fig, path)


def plot_errors(logs, path=None, sigma: float = 2.0, *, truth=None):
    """Estimation error per state with ``±sigma`` standard-deviation bands where ``P`` exists.

    The error axes are scaled to what the errors settle to after the start-up
    transient (the first 10 % of the record, shaded): each estimator's 98th
    percentile of :math:`|\\hat x - x|` and of its band there, an estimator ten
    times worse than the median not setting the scale. Whatever goes far
    beyond the axes (more than half the axis again: the transient, a diverging
    estimator, the wide band of a window estimator with too few samples at
    start-up) is named in the axes' corner with its peak, so nothing is hidden
    without a word.

    Parameters
    ----------
    logs : Log, result, or dict of name -> Log or result
        Runs on the same record: logs, and results of ``filter``, ``smooth`` and
        ``fit`` (with ``truth``).
    path : str or Path, optional
    sigma : float
        Width of the band in standard deviations (2: about 95 % for a
        consistent Gaussian estimator).
    truth : Log or (T, nx) array, optional
        The true states of the results (default: those of the first log that has them).

    Returns
    -------
    matplotlib.figure.Figure
    """
    plt = _pyplot()
    logs, _ = _as_logs(logs, truth, "plot_errors", need_truth=True)
    first = next(iter(logs.values()))
    names = first.state_names or [f"x{i + 1}" for i in range(first.x.shape[1])]
    fig, axes = plt.subplots(len(names), 1, sharex=True, figsize=(7.5, 2.2 * len(names)),
                             constrained_layout=True, squeeze=False)
    settled: list[list[np.ndarray]] = [[] for _ in names]
    peaks: list[list[tuple[float, str, float]]] = [[] for _ in names]
    for k, (label, log) in enumerate(logs.items()):
        err = log.x_hat - log.x
        k0 = startup_samples(len(err))
        for i, ax in enumerate(axes[:, 0]):
            ax.plot(log.t, err[:, i], label=label, **_style(k))
            sd = np.sqrt(np.maximum(log.P[:, i, i], 0.0)) if "P" in log else None
            if sd is not None and not np.isfinite(sd).any():
                sd = None  # no band where no step reported a covariance
            if sd is not None:
                ax.fill_between(log.t, -sigma * sd, sigma * sd, color=f"C{k}", alpha=0.1,
                                lw=0)
            settled[i].append(np.abs(err[k0:, i]))
            if sd is not None:
                settled[i].append(sigma * sd[k0:])
            size = np.abs(err[:, i])
            if np.isfinite(size).any():
                j = int(np.nanargmax(size))
                peaks[i].append((float(size[j]), label, float(log.t[j])))
            if sd is not None:
                j = int(np.nanargmax(sd))
                peaks[i].append((float(sigma * sd[j]), f"{label} band", float(log.t[j])))
    t = first.t
    k0 = startup_samples(len(t))
    for i, ax in enumerate(axes[:, 0]):
        ax.axhline(0.0, color="0.5", lw=0.6)
        if len(t) > 1:
            ax.axvspan(t[0], t[k0], color="0.92", lw=0, zorder=0,
                       label="start-up" if i == 0 else None)
        lim = _settled_limit(settled[i])
        if lim > 0:
            ax.set_ylim(-lim, lim)
            # named when far beyond (a line just past the edge speaks for itself)
            off = sorted((p for p in peaks[i] if p[0] > 1.5 * lim), reverse=True)
            if off:
                text = "beyond the axis: " + "; ".join(
                    f"{who} {size:.3g} at t = {when:g}" for size, who, when in off[:4])
                ax.text(0.01, 0.03, text, transform=ax.transAxes, fontsize=7, color="0.25",
                        va="bottom", ha="left",
                        bbox={"facecolor": "white", "alpha": 0.8, "lw": 0, "pad": 1.5})
        ax.set_ylabel(f"error {names[i]}")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", fontsize="small", ncol=min(3, len(logs) + 1))
    axes[0, 0].set_title(f"estimation error, ±{sigma:g}σ bands where a covariance exists; "
                         f"axes scaled to the settled errors", fontsize="medium")
    axes[-1, 0].set_xlabel(_time_label(first))
    return _finish(fig, path)


def plot_smoothing(result, path=None, *, truth=None, filtered=None, sigma: float = 2.0,
                   states=None, title: str | None = None):
    """The filter against the smoother on one record: per state, the truth, the
    filtered and the smoothed estimates with their ``±sigma`` bands.

    ``plot_smoothing(ekf.smooth(y), truth=log)`` draws the forward pass of the
    Rauch-Tung-Striebel smoother (:math:`\\hat x_{k|k}`, the filter) against its result
    (:math:`\\hat x_{k|T-1}`); the same for ``UKF.smooth`` and ``ParticleFilter.smooth``.
    The legend gives each one's RMSE where the truth is known.

    Parameters
    ----------
    result : SmoothResult, ParticleSmoothResult or another result
        The smoothed estimates; one of a smoother holds the filter's
        (``x_filtered``, ``P_filtered``). Any other result (e.g. a
        :meth:`FullInformation.fit <estim.FullInformation.fit>`) with ``filtered``.
    path : str or Path, optional
        Write the figure there.
    truth : Log or (T, nx) array, optional
        The true states (a log of the same record: e.g. of :func:`~estim.simulate`).
    filtered : Log or result, optional
        The filtered estimates (default: the smoother's own forward pass).
    sigma : float
        Width of the bands in standard deviations.
    states : list of str, optional
        Which states to draw (default all).
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    from estim._validate import as_float

    sigma = as_float(sigma, "sigma", positive=True)
    if not isinstance(result, Estimates):
        raise TypeError(f"result must be the result of a smoother (EKF.smooth, UKF.smooth, "
                        f"ParticleFilter.smooth) or of another whole-record estimate "
                        f"(FitResult, FilterResult), got {type(result).__name__}")
    if filtered is None:
        xf = getattr(result, "x_filtered", None)
        if xf is None:
            raise ValueError(f"a {type(result).__name__} holds no filtered estimates: pass "
                             f"filtered= (e.g. ekf.filter(y) or a Log of replay)")
        import dataclasses

        # the forward pass, as a result of its own (same times and names)
        filtered = dataclasses.replace(  # type: ignore[call-arg]  # (a smoother's P)
            result, x=xf, P=getattr(result, "P_filtered", None))
    runs, truth_log = _as_logs({"filter": filtered, "smoother": result}, truth,
                               "plot_smoothing", need_truth=False)
    smoothed = runs["smoother"]
    names = smoothed.state_names or [f"x{i + 1}" for i in range(smoothed.x_hat.shape[1])]
    if isinstance(states, str):
        states = [states]
    chosen = list(names) if states is None else list(states)
    unknown = [s for s in chosen if s not in names]
    if unknown:
        raise ValueError(f"states {unknown} are not in the result; states are {names}")
    plt = _pyplot()
    fig, axes = plt.subplots(len(chosen), 1, sharex=True, figsize=(7.5, 2.4 * len(chosen)),
                             constrained_layout=True, squeeze=False)
    labels = {}
    for key, log in runs.items():
        labels[key] = key
        if truth_log is not None:
            try:
                labels[key] = f"{key} (RMSE {float(rmse(log)):.3g})"
            except ValueError:  # e.g. a truth of other length: no score
                pass
    for ax, name in zip(axes[:, 0], chosen, strict=True):
        i = names.index(name)
        if truth_log is not None:
            ax.plot(truth_log.t, truth_log.x[:, i], color="black", lw=1.8, label="truth")
        for k, (key, log) in enumerate(runs.items()):
            style = {"color": f"C{k}", "ls": "--" if key == "filter" else "-",
                     "lw": 1.2 if key == "filter" else 1.6}
            ax.plot(log.t, log.x_hat[:, i], label=labels[key], **style)
            if "P" in log and log.P.shape[1] == log.x_hat.shape[1]:
                sd = np.sqrt(np.maximum(log.P[:, i, i], 0.0))
                if np.isfinite(sd).any():
                    ax.fill_between(log.t, log.x_hat[:, i] - sigma * sd,
                                    log.x_hat[:, i] + sigma * sd, color=f"C{k}",
                                    alpha=0.12 if key == "filter" else 0.22, lw=0)
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", fontsize="small", ncol=3)
    axes[0, 0].set_title(title or f"filter and smoother, ±{sigma:g}σ bands",
                         fontsize="medium")
    axes[-1, 0].set_xlabel(_time_label(truth_log if truth_log is not None else smoothed))
    return _finish(fig, path)


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
    ax.set_xlabel(_time_label(log))
    ax.set_ylabel("solve time per step [s]")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize="small")
    return _finish(fig, path)


def plot_posterior(posterior, path=None, *, truth=None, reference=None):
    """The chains of :func:`~estim.inference.pmmh` or
    :func:`~estim.inference.particle_gibbs`: per parameter, the trace of every chain
    (the warm-up shaded) and the histogram of the draws after it.

    Parameters
    ----------
    posterior : estim.inference.Posterior
    path : str or Path, optional
    truth : dict, optional
        Values drawn as vertical lines (the parameters a record was simulated with).
    reference : estim.inference.Posterior, optional
        Other chains of the same posterior (an exact-likelihood run), their histogram
        drawn as a line.
    """
    plt = _pyplot()
    names = posterior.names
    fig, axes = plt.subplots(len(names), 2, figsize=(8, 1.9 * len(names) + 0.6),
                             constrained_layout=True, squeeze=False,
                             gridspec_kw={"width_ratios": [2.2, 1]})
    for i, name in enumerate(names):
        trace, hist = axes[i]
        for c, chain in enumerate(posterior.draws[:, :, i]):
            trace.plot(chain, lw=0.5, color=f"C{c}", alpha=0.8)
        trace.axvspan(0, posterior.warmup, color="0.9", zorder=-1)
        trace.set_ylabel(name)
        draws = posterior.samples(name).ravel()
        hist.hist(draws, bins=50, density=True, color="C0", alpha=0.6, label="chains")
        if reference is not None:
            ref = reference.samples(name).ravel()
            h, edges = np.histogram(ref, bins=50, density=True)
            hist.step(edges[:-1], h, where="post", color="k", lw=1.0, label="reference")
        if truth is not None and name in truth:
            for ax in (trace, hist):
                (ax.axhline if ax is trace else ax.axvline)(truth[name], color="C3", lw=1.2)
        hist.set_yticks([])
    axes[-1, 0].set_xlabel("iteration")
    axes[-1, 1].set_xlabel("value")
    if reference is not None:
        axes[0, 1].legend(fontsize="small")
    acc = posterior.acceptance
    axes[0, 0].set_title(f"{posterior.method}: acceptance {acc.mean():.2f}", fontsize="small")
    return _finish(fig, path)


def plot_state_posterior(states, path=None, *, truth=None, t=None, index: int = 0):
    """The states' posterior of :meth:`Posterior.states
    <estim.inference.Posterior.states>`: the mean of one state and its pointwise 95 %
    band, a few of the paths, and the ``truth`` ``(T, nx)`` if given."""
    plt = _pyplot()
    T = states.x.shape[0]
    t = np.arange(T) if t is None else np.asarray(t)
    fig, ax = plt.subplots(figsize=(7.5, 3.0), constrained_layout=True)
    ax.fill_between(t, states.lower[:, index], states.upper[:, index], color="C0",
                    alpha=0.25, lw=0, label="95 % band")
    for path_ in states.paths[:5, :, index]:
        ax.plot(t, path_, color="C0", lw=0.4, alpha=0.6)
    ax.plot(t, states.x[:, index], color="C0", lw=1.5, label="posterior mean")
    if truth is not None:
        ax.plot(t, np.asarray(truth)[:, index], color="k", lw=1.0, ls="--", label="truth")
    ax.set_ylabel(states.state_names[index])
    ax.set_xlabel("sample" if t is None else "t")
    ax.legend(fontsize="small")
    return _finish(fig, path)


def plot_particles(particles, path=None, *, t=None, weights=None, truth=None,
                   state: int = 0, name: str | None = None, max_particles: int = 200,
                   seed: int = 0):
    """The particle cloud of one state over time: each sample's particles as dots
    (their size by weight when ``weights`` are given), the weighted mean and, if given,
    the truth.

    Parameters
    ----------
    particles : (T, N, nx) array
        The particles after each sample's update (before or after resampling).
    path : str or Path, optional
        Write the figure there.
    t : (T,) array, optional
        Sample times (default 0, 1, ...).
    weights : (T, N) array, optional
        Normalised weights (default equal: resampled particles).
    truth : (T, nx) array, optional
    state : int
        The state drawn.
    name : str, optional
        The y label (default ``x{state + 1}``).
    max_particles : int
        At most this many particles per sample are drawn (a random subset, by
        ``seed``: clouds of thousands stay readable); the mean is over all.
    seed : int
    """
    X = np.asarray(particles, dtype=float)
    if X.ndim == 2:
        X = X[..., None]
    if X.ndim != 3:
        raise ValueError(f"particles must be (T, N, nx), got shape {X.shape}")
    T, N, nx = X.shape
    if not 0 <= state < nx:
        raise ValueError(f"state must be in 0..{nx - 1}, got {state}")
    W = np.full((T, N), 1.0 / N) if weights is None else np.asarray(weights, dtype=float)
    if W.shape != (T, N):
        raise ValueError(f"weights must be (T, N) = {(T, N)}, got shape {W.shape}")
    tt = np.arange(T) if t is None else np.asarray(t, dtype=float)
    if tt.shape != (T,):
        raise ValueError(f"t must have {T} entries, got shape {tt.shape}")
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 3.2), constrained_layout=True)
    pick = np.random.default_rng(seed).permutation(N)[:min(N, max_particles)]
    size = 4.0 * W[:, pick] * N if weights is not None else np.full((T, pick.size), 2.0)
    ax.scatter(np.repeat(tt, pick.size), X[:, pick, state].ravel(),
               s=np.clip(size.ravel(), 0.2, 20.0), color="C0", alpha=0.15, lw=0,
               label=f"particles ({pick.size} of {N} drawn)")
    ax.plot(tt, np.sum(W * X[..., state], axis=1), color="C1", lw=1.5,
            label="weighted mean")
    if truth is not None:
        ax.plot(tt, np.asarray(truth, dtype=float)[:, state], color="k", lw=1.0, ls="--",
                label="truth")
    ax.set_ylabel(name or f"x{state + 1}")
    ax.set_xlabel("t" if t is not None else "sample")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small", loc="upper right")
    return _finish(fig, path)
