"""Tasks on joblib or dask workers: the engine under :func:`~estim.compare`'s runs and
the chains of :mod:`estim.inference`.

:func:`run_tasks` calls one function on each of a list of argument tuples, in this
process (``n_jobs=1``), on a joblib backend (``"loky"`` processes, ``"threading"``, or an
external backend such as ``"dask"`` that joblib registers lazily), or straight on the
active ``dask.distributed`` client (``backend="dask"``: a local or remote cluster), and
returns the results in the order of the tasks.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["run_tasks"]


def run_tasks(fn: Callable[..., Any], tasks: Sequence[tuple], *, n_jobs: int = 1,
              backend: str = "loky") -> list[Any]:
    """``[fn(*args) for args in tasks]``, on ``n_jobs`` workers of ``backend`` (see the
    module); in this process when ``n_jobs == 1`` and the backend is not dask."""
    if backend == "dask":
        from dask.distributed import get_client

        client = get_client()
        return client.gather([client.submit(fn, *a, pure=False) for a in tasks])
    if n_jobs == 1:
        return [fn(*a) for a in tasks]
    import joblib.parallel as jp
    from joblib import Parallel, delayed

    if backend not in jp.BACKENDS and backend in getattr(jp, "EXTERNAL_BACKENDS", {}):
        jp.EXTERNAL_BACKENDS[backend]()  # joblib registers dask/ray lazily
    return Parallel(n_jobs=n_jobs, backend=backend, verbose=0, batch_size=1)(
        delayed(fn)(*a) for a in tasks)
