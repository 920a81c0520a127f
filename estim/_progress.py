"""Progress of long work: tqdm bars (its notebook front end in Jupyter), shown only to
someone watching and only when the work is slow.

Every operation of estim that can take more than a few seconds (a comparison, a particle
filter or smoother over a record, a full-information fit, the first compilation of code for
this machine, ``estim run``) reports through :func:`bar`. A bar appears once the work has
lasted ``delay`` seconds (quick work stays silent), on a terminal or in Jupyter (the
notebook widget where ipywidgets is installed, else the text bar); never
when stderr is redirected (a log file, CI, pytest's capture). The environment variable
``ESTIM_PROGRESS`` overrides the choice: ``0`` (or ``false``, ``off``) for silence,
``1`` to show bars even when stderr is not a terminal. An operation's own ``progress=``
argument (``compare``) overrides both.
"""

from __future__ import annotations

import os
import shutil
import sys
import time
from typing import Any

__all__ = ["ENV", "bar", "enabled"]

#: the environment variable that turns the bars off (0) or on (1) everywhere
ENV = "ESTIM_PROGRESS"

#: seconds of work before a bar appears (tqdm's ``delay``)
DELAY = 2.0


def _in_jupyter() -> bool:
    """Whether this is a Jupyter kernel (an IPython shell with a kernel application)."""
    ipython = sys.modules.get("IPython")
    if ipython is None or not hasattr(ipython, "get_ipython"):
        return False
    shell = ipython.get_ipython()
    return shell is not None and "IPKernelApp" in getattr(shell, "config", {})


def _watched() -> bool:
    """Whether someone is watching: stderr is a terminal, or this is a Jupyter kernel."""
    try:
        if sys.stderr is not None and sys.stderr.isatty():
            return True
    except (AttributeError, ValueError):  # a replaced or closed stderr
        pass
    return _in_jupyter()


def enabled(show: bool | None = None) -> bool:
    """Whether bars are shown: ``show`` when given, else :data:`ENV` when set, else
    whether someone is watching."""
    if show is not None:
        return bool(show)
    value = os.environ.get(ENV, "").strip().lower()
    if value in ("0", "false", "no", "off"):
        return False
    if value in ("1", "true", "yes", "on"):
        return True
    return _watched()


class _NoBar:
    """What :func:`bar` gives when no bar is shown: the same calls, doing nothing."""

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix_str(self, text: str) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> _NoBar:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


class _Delayed:
    """A tqdm bar made only once its work has lasted ``delay`` seconds (at an ``update``
    after that): quick work draws nothing on any front end (the notebook's does not
    follow tqdm's own ``delay``)."""

    def __init__(self, make, delay: float) -> None:
        self._make, self._delay = make, delay
        self._t0 = time.monotonic()
        self._bar: Any = None
        self._count = 0
        self._postfix = ""

    def update(self, n: int = 1) -> None:
        if self._bar is None:
            self._count += n
            if time.monotonic() - self._t0 < self._delay:
                return
            self._bar = self._make(self._count, self._t0)
            if self._postfix:
                self._bar.set_postfix_str(self._postfix)
        else:
            self._bar.update(n)

    def set_postfix_str(self, text: str) -> None:
        if self._bar is None:
            self._postfix = text
        else:
            self._bar.set_postfix_str(text)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def __enter__(self) -> _Delayed:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _front_end():
    """tqdm's class: the notebook widget in Jupyter where ipywidgets is installed, else
    the text bar (on stderr)."""
    if _in_jupyter():
        try:
            import ipywidgets  # noqa: F401 - the widget needs it
            from tqdm.notebook import tqdm
            return tqdm
        except ImportError:
            pass
    from tqdm import tqdm
    return tqdm


def bar(total: int | None = None, desc: str = "", unit: str = "it",
        show: bool | None = None, delay: float | None = None, clock: bool = False) -> Any:
    """A tqdm bar over ``total`` steps of ``unit`` (None: a count with elapsed time;
    ``clock``: the elapsed time alone, for work without steps), shown after ``delay``
    seconds (default :data:`DELAY`) when :func:`enabled` (else one that does nothing).
    Use it as a context manager, or ``update`` and ``close`` it."""
    if not enabled(show):
        return _NoBar()
    try:
        tqdm = _front_end()
    except ImportError:  # pragma: no cover - tqdm is a dependency
        return _NoBar()

    def make(done: int, t0: float) -> Any:
        # the terminal's size (80 x 24 where it reports none, e.g. a pseudo-terminal of
        # size 0, where tqdm would hide the bar)
        size = shutil.get_terminal_size()
        made = tqdm(total=total, desc=desc, unit=unit, leave=False, initial=done,
                    ncols=size.columns, nrows=size.lines,
                    bar_format="{desc}: {elapsed}" if clock else None)
        # the clock from the start of the work, on tqdm's own clock
        made.start_t = made.last_print_t = made._time() - (time.monotonic() - t0)
        made.refresh()
        return made

    return _Delayed(make, DELAY if delay is None else delay)
