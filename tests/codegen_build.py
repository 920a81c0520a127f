"""How tests/test_codegen.py and tests/test_codegen_mhe.py build an export of
``estim.codegen`` (imported as ``from codegen_build import build``): the driver with
every warning an error, CasADi's generated code with the Makefile's flags."""

from __future__ import annotations

import shlex
import shutil
import subprocess
from pathlib import Path

from estim import codegen
from estim._compile import compiler

#: Warnings that fail the build of the driver ``<name>.c``. CasADi's generated
#: ``<name>_functions.c`` is compiled with the Makefile's flags only: -Wextra reports
#: the parameters its functions take and do not use (``iw``, ``w``, ``mem``), which is
#: CasADi's code generator's to change, not the export's.
STRICT = "-Wall -Wextra -Werror"


def commands(cc: str, name: str) -> list[list[str]]:
    """The commands that build ``lib<name>.so``: with the Makefile if there is make
    (first the driver's object with the strict flags added, then the library, which
    compiles ``<name>_functions.c`` with the Makefile's own flags), else with ``cc``
    alone."""
    if shutil.which("make"):
        return [["make", f"CC={cc}", f"CFLAGS={codegen.CFLAGS} {STRICT}", f"{name}.o"],
                ["make", f"CC={cc}", f"lib{name}.so"]]
    flags = codegen.CFLAGS.split()
    return [[cc, *flags, *STRICT.split(), "-c", f"{name}.c", "-o", f"{name}.o"],
            [cc, *flags, "-c", f"{name}_functions.c", "-o", f"{name}_functions.o"],
            [cc, "-shared", f"{name}.o", f"{name}_functions.o", "-o", f"lib{name}.so", "-lm"]]


def build(directory: Path, name: str) -> Path:
    """Build ``lib<name>.so`` in ``directory`` (see :func:`commands`) and return its path;
    a command that fails fails the test with its error output."""
    cc = compiler()[0]
    for command in commands(cc, name):
        run = subprocess.run(command, cwd=directory, capture_output=True, text=True,
                             check=False)
        assert run.returncode == 0, f"{shlex.join(command)} failed:\n{run.stdout}{run.stderr}"
    return Path(directory) / f"lib{name}.so"
