r"""C code of a fused Kalman filter (:class:`~estim.EKF`, :class:`~estim.UKF`) for
deployment without Python or CasADi.

:func:`export` writes CasADi's generated C code of the filter's two step functions
(update only for the first sample, prediction and update for every later one), a
small hand-written driver that does what :meth:`~estim.Estimator.step` does with
their results (the gate, the suspect flag, the recovery of a failed update with its
last trusted estimate), a ``Makefile`` and a ``README.md``. The code is plain C99
with ``<math.h>`` and ``<string.h>`` only: no allocation, no CasADi runtime.

The real-time iteration of the moving horizon estimator (:class:`~estim.MHE` with
``rti=True``) is exported the same way: CasADi's generated code of the window's
preparation, feedback and cost (:func:`estim.solvers.least_squares.rti.build`), of the arrival
covariance's step and of the model's transition, and a driver that does the window's
bookkeeping as the Python estimator does, in the same order (see
``docs/deployment.md``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

from estim._validate import as_choice
from estim.codegen import kalman, mhe
from estim.codegen.files import CFLAGS as CFLAGS
from estim.codegen.files import OPTIMIZE, cflags, check_model

if TYPE_CHECKING:
    from estim.estimators.kalman.ekf import EKF
    from estim.estimators.kalman.ukf import UKF
    from estim.estimators.window.mhe import MHE

__all__ = ["export"]

#: Status codes of ``<name>_step`` (the C enum), with the Python status they stand for.
STATUS = kalman.STATUS

#: Status codes of the MHE's ``<name>_step`` and ``<name>_prepare``.
MHE_STATUS = mhe.STATUS


def export(estimator: EKF | UKF | MHE, directory: str | Path, *, name: str | None = None,
           overwrite: bool = False, optimize: str = "speed") -> dict[str, Path]:
    r"""Write C code of an EKF, a UKF or a real-time iteration MHE that steps as
    :meth:`~estim.Estimator.step` does.

    Files written into ``directory`` (created if needed):

    ``<name>_functions.c``, ``<name>_functions.h``
        CasADi's generated code of the filter's two step functions,
        ``<name>_update`` (the first sample) and ``<name>_predict_update``, each
        ``(s, w, y, tuning) -> (s_new, innovation, flags, s_prior)`` with the filter
        state :math:`s = [x; \operatorname{vec}(P)]` (column-major,
        :math:`n_x + n_x^2`), the transition's input :math:`w` and the tuning
        :math:`[\operatorname{vec}(Q); \operatorname{vec}(R)]`. The model, its
        parameters, the sigma-point weights, the bounds of ``clip`` and the
        :math:`\chi^2` limits of the suspect flag and of ``gate`` are constants in it.
    ``<name>.h``, ``<name>.c``
        The driver: a struct ``<name>_t`` holding the filter state, the tuning
        (``Q``, ``R``, ``x0``, ``P0``: the estimator's at export time, settable) and
        all work memory (its size is fixed at export time and given in the README);
        ``<name>_init``, ``<name>_reset``, ``<name>_step`` (returns 0 ok, 1 suspect,
        2 rejected by the gate, 3 failed and kept the prediction, 4 failed and
        re-anchored on the last trusted estimate with :math:`P + P_0`, -1 for an
        ``inf`` in ``y`` or a non-finite ``u``), ``<name>_nis`` and
        ``<name>_set_tuning``.
    ``Makefile``
        Builds ``lib<name>.a`` and ``lib<name>.so`` (``cc -O2 -fPIC`` without
        contraction into fused multiply-adds).
    ``README.md``
        The API, the memory and the build.
    ``<name>_example.c``
        A program that runs the estimator over a recorded CSV file (the outputs, then
        the inputs, one sample per line; ``nan`` for a missing output) and writes the
        statuses, estimates and standard deviations as CSV: ``make example``.

    NaN in ``y`` marks a missing output, as in Python. For a model with sampled
    inputs (``hold="foh"``) the driver keeps the previous input, as ``step`` does.
    For a model with ``variable_dt=True`` the step takes the interval since the
    previous sample after ``u`` (``<name>_step(f, y, u, dt, x_hat, P)``, and the
    MHE's ``<name>_prepare(e, u, dt)``; a ``dt`` not positive and finite is refused
    with -1), and the example program reads the time stamp from the record's first
    column.

    A filter with ``form="sqrt"`` is exported in its square-root form: the filter
    state is :math:`s = [x; \operatorname{vec}(S)]`, :math:`P = S S^\top`, the step
    functions read the tuning :math:`[\operatorname{vec}(L_Q);
    \operatorname{vec}(L_R)]`, and ``<name>_functions.c`` also holds
    ``<name>_noise_factors``, ``<name>_cholesky``, ``<name>_add_P0`` (the factor
    :math:`\operatorname{tria}([S, \operatorname{chol}(P_0)])` of :math:`P + P_0` that
    the gate and the recovery keep) and ``<name>_covariance`` (:math:`S S^\top`, the
    covariance the step writes); the struct's ``Q``, ``R`` and ``P0`` stay covariances.

    For an :class:`~estim.MHE` with ``rti=True`` the same files hold the
    generated ``<name>_prepare_window``, ``<name>_feedback_window``,
    ``<name>_window_cost``, ``<name>_cov_step`` and ``<name>_transition``, and a
    driver with ``<name>_init``, ``<name>_reset``, ``<name>_prepare(e, u)`` (the
    preparation phase, :meth:`~estim.MHE.prepare`), ``<name>_step(e, y, u, x_hat,
    P)`` (0 ok, 1 inexact start-up, 2 suspect, -1 invalid argument, -2 a non-finite step, where
    Python falls back to its converged solver: reset needed, -3 ``u`` is not the
    input given to prepare), ``<name>_iterations`` and ``<name>_size``. The window,
    the arrival cost (every ``arrival_cost``), the start-up's projected Gauss-Newton
    iterations and the bounds are those of the estimator.

    Parameters
    ----------
    estimator : EKF, UKF or MHE
        The estimator (its tuning, options and bounds are what the code does); an
        MHE with ``rti=True``.
    directory : str or Path
        Where the files go.
    name : str, optional
        The C identifier that prefixes every file and symbol, default
        ``"<filter>_<model name>"`` made an identifier (e.g. ``ekf_batch_reactor``).
    overwrite : bool
        Replace files of the same names in ``directory`` (refused by default).
    optimize : {"speed", "size"}
        The Makefile's optimisation: ``-O2`` (the step's speed) or ``-Os`` (the
        library's size). Neither changes the arithmetic (no fused multiply-adds, no
        fast math): the results are the same doubles. See the deployment page for
        the sizes, build times and step times of both.

    Returns
    -------
    dict
        The paths written, by kind: ``"functions_c"``, ``"functions_h"``, ``"h"``,
        ``"c"``, ``"makefile"``, ``"readme"``, ``"example"``.

    Raises
    ------
    TypeError
        ``estimator`` is not an :class:`~estim.EKF`, :class:`~estim.UKF` or
        :class:`~estim.MHE`.
    ValueError
        An invalid ``name``; a model integrated by CVODES (``integrator="cvodes"``,
        which needs the CasADi runtime); an MHE without ``rti=True`` or with
        ``horizon=1``.
    FileExistsError
        A file to write exists and ``overwrite`` is False.
    """
    from estim.estimators.window.mhe import MHE

    _exportable(estimator)
    m = estimator.model
    if name is None:
        name = re.sub(r"\W+", "_", f"{estimator.name}_{m.name}".lower()).strip("_")
        if name[:1].isdigit():
            name = f"f_{name}"
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise ValueError(f"name must be a C identifier, got {name!r}")
    directory = Path(directory)
    paths = {"functions_c": directory / f"{name}_functions.c",
             "functions_h": directory / f"{name}_functions.h",
             "h": directory / f"{name}.h", "c": directory / f"{name}.c",
             "makefile": directory / "Makefile", "readme": directory / "README.md",
             "example": directory / f"{name}_example.c"}
    flags = cflags(as_choice(optimize, tuple(OPTIMIZE), "optimize"))
    existing = [p.name for p in paths.values() if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{directory} already holds {', '.join(existing)}: pass "
                              f"overwrite=True to replace them")
    directory.mkdir(parents=True, exist_ok=True)
    if isinstance(estimator, MHE):
        mhe.write(estimator, directory, name, paths, flags)
    else:
        kalman.write(estimator, directory, name, paths, flags)
    return paths


def memory(estimator: EKF | UKF | MHE) -> int:
    """Bytes of the struct ``<name>_t`` that :func:`export` writes for ``estimator``
    (8-byte doubles, pointers and ``casadi_int``; the filter state, the tuning, the
    step's results and CasADi's work arrays; in the square-root form also the factor
    of ``P0``; for the MHE also the window, the arrival cost and the real-time
    iteration's intermediate results). Refuses what :func:`export` refuses, with its
    errors."""
    from estim.estimators.window.mhe import MHE

    _exportable(estimator)
    if isinstance(estimator, MHE):
        return mhe.memory(estimator)
    return kalman.memory(estimator)


def _exportable(estimator: object) -> None:
    """A ``TypeError`` or ``ValueError`` (as :func:`export` documents them) for an
    estimator the export does not handle."""
    from estim.estimators.kalman.fused import FusedKalman
    from estim.estimators.window.mhe import MHE

    if not isinstance(estimator, (FusedKalman, MHE)):
        raise TypeError(f"estimator must be an estim.EKF, estim.UKF or estim.MHE with "
                        f"rti=True, got {type(estimator).__name__}")
    if isinstance(estimator, MHE):
        mhe.check(estimator)
    else:
        check_model(estimator.model)
