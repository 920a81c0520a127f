r"""CasADi Functions compiled to machine code once per machine, kept in a user cache.

:func:`compiled` generates the C code of a Function (CasADi's code generator),
compiles it into a shared library with the system C compiler and loads it
(``casadi.external``). The library is kept in a per-user cache directory under a
key that hashes the generated code, the compiler (its path and version), the
flags and the CasADi version, so a later process, or a parallel worker, loads it
instead of compiling (a few milliseconds against seconds).

The cache directory is ``$ESTIM_CACHE_DIR`` if set, else
``$XDG_CACHE_HOME/estim`` (``~/.cache/estim``; ``%LOCALAPPDATA%\estim`` on
Windows), created with private permissions (``0700``); never the current
directory. Each entry is a library and a small JSON record holding its key and the
SHA-256 of the library: an entry whose record is missing, unreadable, of another
key, or whose library does not match its hash or does not load is compiled again.
Libraries are written under a temporary name and renamed into place, so processes
compiling the same Function at once never see a partial file.

Without a C compiler (``$CC`` if set, else ``cc``, ``gcc`` or ``clang`` on the ``PATH``)
:func:`compiled` raises :class:`CompilerUnavailable`, whose message says what to
install; callers that have an interpreted path fall back to it.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import casadi as ca

from estim import _progress as progress
from estim._progress import bar as progress_bar
from estim.exceptions import CompilerUnavailable

#: Flags of every compilation: optimised, position-independent, no fast-math (the
#: generated code then computes what CasADi's interpreter computes, operation for
#: operation).
FLAGS = ("-O2", "-fPIC", "-shared", "-fno-fast-math", "-ffp-contract=off")

#: The CasADi version, part of every cache key (CasADi's stubs omit the module's
#: ``__version__``).
CASADI_VERSION: str = ca.__version__  # type: ignore[attr-defined]

_LOCK = threading.Lock()
_COMPILER: dict[str, tuple[str, str] | None] = {}
_LOADED: dict[str, ca.Function] = {}
_LIBRARIES: dict[str, ctypes.CDLL] = {}


def cache_directory() -> Path:
    """The cache directory (created, mode 0700): ``$ESTIM_CACHE_DIR``, else the user's
    cache directory followed by ``estim``."""
    env = os.environ.get("ESTIM_CACHE_DIR")
    if env:
        path = Path(env).expanduser()
    elif sys.platform == "win32":
        path = Path(os.environ.get("LOCALAPPDATA", Path.home() / "AppData" / "Local")) / "estim"
    else:
        base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
        path = Path(base) / "estim"
    path = path.absolute()
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    return path


def compiler() -> tuple[str, str] | None:
    """``(path, version line)`` of the C compiler: ``$CC`` when it is set, else the first
    of ``cc``, ``gcc`` and ``clang`` on the ``PATH``; None when there is none."""
    cc = os.environ.get("CC", "")
    with _LOCK:
        if cc in _COMPILER:
            return _COMPILER[cc]
    found = None
    for name in [cc] if cc else ["cc", "gcc", "clang"]:  # $CC, when set, and only it
        path = shutil.which(name)
        if path is None:
            continue
        try:
            run = subprocess.run([path, "--version"], capture_output=True, text=True,
                                 timeout=30, check=False)
        except (OSError, subprocess.SubprocessError):
            continue
        if run.returncode == 0:
            found = (path, (run.stdout.strip().splitlines() or [""])[0])
            break
    with _LOCK:
        _COMPILER[cc] = found
    return found


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def compiled(fun: ca.Function) -> ca.Function:
    """``fun`` as a compiled library, from the cache or compiled now (then cached).

    Parameters
    ----------
    fun : casadi.Function
        Any Function CasADi can generate C code for.

    Returns
    -------
    casadi.Function
        The loaded library's Function (same name, inputs and outputs).

    Raises
    ------
    CompilerUnavailable
        No C compiler, a compilation that failed, or a cache directory that cannot be
        written (the message says why).
    """
    cc = _compiler_or_raise()
    name = fun.name()
    gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
    gen.add(fun)
    code = gen.dump()
    key = _key(code, FLAGS, cc)
    with _LOCK:
        if key in _LOADED:
            return _LOADED[key]
    lib, record = _paths(name, key)
    loaded = _load(lib, record, key, name)
    if loaded is None:
        _built(code, lib, record, key, cc[0], FLAGS)
        loaded = _load(lib, record, key, name)
        if loaded is None:
            raise CompilerUnavailable(f"the library compiled for {name} does not load")
    with _LOCK:
        _LOADED[key] = loaded
    return loaded


def shared_library(code: str, name: str, flags: tuple[str, ...] = FLAGS) -> ctypes.CDLL:
    """C source ``code`` compiled with ``flags`` into a shared library, from the cache or
    compiled now (then cached) as :func:`compiled` does, loaded with :mod:`ctypes`.

    Raises
    ------
    CompilerUnavailable
        As :func:`compiled`.
    """
    cc = _compiler_or_raise()
    key = _key(code, flags, cc)
    with _LOCK:
        if key in _LIBRARIES:
            return _LIBRARIES[key]
    lib, record = _paths(name, key)
    if not _current(lib, record, key):
        _built(code, lib, record, key, cc[0], flags)
    try:
        loaded = ctypes.CDLL(str(lib))
    except OSError as exc:
        raise CompilerUnavailable(f"the library compiled for {name} does not load ({exc})"
                                  ) from None
    with _LOCK:
        _LIBRARIES[key] = loaded
    return loaded


def _compiler_or_raise() -> tuple[str, str]:
    """The C compiler, or :class:`CompilerUnavailable` saying what to install."""
    cc = compiler()
    if cc is None:
        looked = f"$CC = {os.environ['CC']!r}" if os.environ.get("CC") else \
            "cc, gcc or clang on the PATH"
        raise CompilerUnavailable(
            f"no C compiler found ({looked}): install one (e.g. 'apt install gcc', Xcode's "
            "command line tools, or MSVC/MinGW) to compile; the interpreted CasADi path is "
            "used meanwhile")
    return cc


def _key(code: str, flags: tuple[str, ...], cc: tuple[str, str]) -> str:
    """The cache key of ``code`` built with ``flags`` by ``cc``."""
    return hashlib.sha256("\n".join(
        [code, *cc, " ".join(flags), CASADI_VERSION, platform.machine(), sys.platform]
    ).encode()).hexdigest()


def _paths(name: str, key: str) -> tuple[Path, Path]:
    """The cached library's path and its record's path (the directory created)."""
    try:
        root = cache_directory()
    except OSError as exc:
        raise CompilerUnavailable(f"the compile cache directory cannot be created ({exc}); "
                                  f"set ESTIM_CACHE_DIR to a writable directory") from None
    lib = root / f"{name}-{key[:24]}{'.dll' if sys.platform == 'win32' else '.so'}"
    return lib, lib.with_suffix(".json")


def _built(code: str, lib: Path, record: Path, key: str, cc: str,
           flags: tuple[str, ...]) -> None:
    """:func:`_build`, with an unwritable cache reported as :class:`CompilerUnavailable`."""
    try:
        _build(code, lib, record, key, cc, lib.parent, flags)
    except OSError as exc:
        raise CompilerUnavailable(f"the compile cache {lib.parent} is not writable ({exc}); "
                                  f"set ESTIM_CACHE_DIR to a writable directory") from None


def _current(lib: Path, record: Path, key: str) -> bool:
    """Whether the cached library's record names ``key`` and its hash matches."""
    try:
        meta = json.loads(record.read_text())
        return meta.get("key") == key and meta.get("sha256") == _sha256(lib)
    except (OSError, ValueError):
        return False


def _load(lib: Path, record: Path, key: str, name: str) -> ca.Function | None:
    """The cached library if its record names ``key`` and its hash matches, else None."""
    if not _current(lib, record, key):
        return None
    try:
        return ca.external(name, str(lib))
    except RuntimeError:
        return None


def _compile_watched(command: list[str], cwd: str, what: str
                     ) -> subprocess.CompletedProcess:
    """Run the compiler (at most 600 s), with a bar saying ``what`` once it has taken
    more than a second (:mod:`estim._progress`: on a terminal or in Jupyter)."""
    with subprocess.Popen(command, cwd=cwd, stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True) as proc, \
            progress_bar(None, what, delay=min(1.0, progress.DELAY), clock=True) as bar:
        t0 = time.monotonic()
        bar.update(0)  # (shown at once when there is no delay)
        while True:
            try:
                out, err = proc.communicate(timeout=0.5)
                break
            except subprocess.TimeoutExpired:
                bar.update(0)  # the bar's clock, shown after its delay
                if time.monotonic() - t0 > 600:
                    proc.kill()
                    raise
    return subprocess.CompletedProcess(command, proc.returncode, out, err)


def _build(code: str, lib: Path, record: Path, key: str, cc: str, root: Path,
           flags: tuple[str, ...] = FLAGS) -> None:
    """Compile ``code`` with ``flags`` into ``lib`` (through a temporary name) and write its
    record."""
    with tempfile.TemporaryDirectory(dir=root, prefix="build-") as tmp:
        src = Path(tmp) / "code.c"
        src.write_text(code)
        out = Path(tmp) / lib.name
        try:
            # relative names, so that every build of the same code gives the same bytes
            run = _compile_watched([cc, *flags, src.name, "-o", out.name, "-lm"], tmp,
                                   f"compiling {lib.stem.rsplit('-', 1)[0]}, once per machine")
        except (OSError, subprocess.SubprocessError) as exc:
            raise CompilerUnavailable(f"running the C compiler {cc} failed: {exc}") from None
        if run.returncode != 0:
            raise CompilerUnavailable(f"the C compiler {cc} failed: "
                                      f"{(run.stderr or run.stdout).strip()[:500]}")
        digest = _sha256(out)
        os.replace(out, lib)
    tmp_record = record.with_name(f"{record.name}.{os.getpid()}.{threading.get_ident()}")
    tmp_record.write_text(json.dumps({"key": key, "sha256": digest, "compiler": cc,
                                      "flags": list(flags), "casadi": CASADI_VERSION}))
    os.replace(tmp_record, record)
