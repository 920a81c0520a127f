"""The shape of the code base (docs/architecture.md): layers without circles, no room too
big to read.

The layer contracts are those of ``[tool.importlinter]`` in pyproject.toml, which
``lint-imports`` checks in .ci/run; this module checks them again over the syntax trees,
so that the suite enforces them without import-linter installed: every ``import`` and
``from ... import`` of an estim module, at module level or inside a function, counts;
those under ``if TYPE_CHECKING:`` (annotations only) do not.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "estim"
#: The largest module and the largest class, in lines, unless a comment at the top of the
#: module says why it is longer (``# long module: <why>``, ``# long class <Name>: <why>``).
MODULE_LINES, CLASS_LINES = 600, 300
#: The most modules side by side in a package of the rooms that grow by family (their
#: subpackages and ``__init__`` not counted): more, and they are split by family.
FAMILY_ROOMS, ROOM_MODULES = ("estimators", "solvers", "inference"), 12

try:
    import tomllib
except ImportError:  # Python 3.10
    tomllib = pytest.importorskip("tomli")


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


MODULES = _modules()


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """The nodes under ``if TYPE_CHECKING:`` (not its ``else``)."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for stmt in node.body:
                skip.update(id(n) for n in ast.walk(stmt))
    return skip


def _resolve(name: str) -> str | None:
    """The estim module ``name`` stands for: itself, or its nearest enclosing module."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _imports(name: str) -> dict[str, int]:
    """The estim modules that module ``name`` imports, with the line of the first import."""
    path = MODULES[name]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    skip = _type_checking_nodes(tree)
    found: dict[str, int] = {}
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        targets = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            # "from estim import models" imports the module estim.models
            targets = [f"{module}.{a.name}" if f"{module}.{a.name}" in MODULES else module
                       for a in node.names]
        for target in targets:
            if target == "estim" or target.startswith("estim."):
                resolved = _resolve(target)
                if resolved and resolved != name:
                    found.setdefault(resolved, node.lineno)
    return found


GRAPH = {name: _imports(name) for name in MODULES}


def _contracts() -> list[dict]:
    with open(ROOT / "pyproject.toml", "rb") as f:
        return tomllib.load(f)["tool"]["importlinter"]["contracts"]


def _within(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def test_the_import_graph_is_read():
    # the reading above sees module-level, function-level and relative imports
    assert "estim.model" in GRAPH["estim.estimators.base"]
    assert "estim.estimators.base" in GRAPH["estim.simulate"]
    assert len(GRAPH) > 60 and sum(map(len, GRAPH.values())) > 150


def test_no_import_circles():
    """Tarjan's strongly connected components of the import graph: all single modules."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []
    counter = [0]
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in GRAPH[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    for v in GRAPH:
        if v not in index:
            visit(v)
    assert not circles, f"import circles: {circles}"


@pytest.mark.parametrize("contract", [c for c in _contracts() if c["type"] == "layers"],
                         ids=lambda c: c["containers"][0])
def test_layers(contract):
    """Each module imports only from its own layer's non-independent siblings (``:``) and
    from the layers below."""
    (container,) = contract["containers"]
    where: dict[str, tuple[int, int, bool]] = {}  # prefix -> (layer, sibling, independent)
    for level, layer in enumerate(reversed(contract["layers"])):
        independent = "|" in layer
        for sibling, part in enumerate(layer.replace("|", ":").split(":")):
            # "(name)": an optional layer, one that may not exist yet
            where[f"{container}.{part.strip().strip('()')}"] = (level, sibling, independent)

    def layer_of(module: str):
        for prefix, place in where.items():
            if _within(module, prefix):
                return prefix, place
        return None, None

    broken = []
    for source, targets in GRAPH.items():
        src_prefix, src = layer_of(source)
        if src is None:
            continue
        for target, line in targets.items():
            dst_prefix, dst = layer_of(target)
            if dst is None or dst_prefix == src_prefix:
                continue
            upward = dst[0] > src[0]
            between_independent = dst[0] == src[0] and src[2]
            if upward or between_independent:
                broken.append(f"{source} -> {target} (line {line})")
    assert not broken, "imports against the layers:\n" + "\n".join(broken)
    listed = {p.rsplit(".", 1)[1] for p in where}
    present = {m[len(container) + 1:].split(".")[0] for m in MODULES
               if m.startswith(container + ".")}
    assert present <= listed | {"__main__"}, f"modules in no layer: {sorted(present - listed)}"


def test_only_the_entry_points_import_the_package_itself():
    """``import estim`` from inside estim loads every layer: only the package's own
    ``__init__`` and the command line may."""
    allowed = {"estim", "estim.cli", "estim.__main__"}
    offenders = []
    for name, path in MODULES.items():
        if name in allowed:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        skip = _type_checking_nodes(tree)
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            if isinstance(node, ast.Import) and any(a.name == "estim" for a in node.names):
                offenders.append(f"{name}:{node.lineno}")
            elif isinstance(node, ast.ImportFrom) and node.module == "estim" and not node.level \
                    and any(f"estim.{a.name}" not in MODULES for a in node.names):
                offenders.append(f"{name}:{node.lineno}")
    assert not offenders, f"imports of the package estim itself: {offenders}"


def test_no_room_too_big():
    too_big = []
    for name, path in MODULES.items():
        text = path.read_text(encoding="utf-8")
        head = "\n".join(line for line in text.splitlines()[:40] if line.startswith("#"))
        lines = text.count("\n")
        if lines > MODULE_LINES and "# long module:" not in head:
            too_big.append(f"module {name}: {lines} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef):
                size = node.end_lineno - node.lineno + 1
                if size > CLASS_LINES and f"# long class {node.name}:" not in head:
                    too_big.append(f"class {name}.{node.name}: {size} lines")
    assert not too_big, "over the size limits (or say why at the top):\n" + "\n".join(too_big)


def test_no_room_too_crowded():
    """``estim/estimators``, ``estim/solvers``, ``estim/inference`` and every package inside
    them hold at most :data:`ROOM_MODULES` modules side by side (docs/architecture.md:
    families as subpackages)."""
    crowded = []
    for room in FAMILY_ROOMS:
        inner = [p.parent for p in (PACKAGE / room).rglob("*/__init__.py")]
        for folder in [PACKAGE / room, *inner]:
            n = len([p for p in folder.glob("*.py") if p.name != "__init__.py"])
            if n > ROOM_MODULES:
                crowded.append(f"{folder.relative_to(ROOT)}: {n} modules")
    assert not crowded, "group these by family:\n" + "\n".join(crowded)


def test_import_linter_agrees():
    """The same contracts checked by import-linter itself (in the test extra)."""
    exe = shutil.which("lint-imports") or str(Path(sys.executable).parent / "lint-imports")
    if not Path(exe).exists():
        pytest.skip("import-linter is not installed (pip install 'estim[test]')")
    res = subprocess.run([exe, "--no-cache"], cwd=ROOT, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    assert " 0 broken" in res.stdout, res.stdout
    assert len(_contracts()) == res.stdout.count(" KEPT")


def test_examples_do_not_import_benchmarks():
    offenders = []
    for path in sorted((ROOT / "examples").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            if any(n == "benchmarks" or n.startswith("benchmarks.") for n in names):
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
            if isinstance(node, ast.Constant) and isinstance(node.value, str) \
                    and "benchmarks" in node.value and "sys.path" in node.value:
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not offenders, f"examples importing benchmarks: {offenders}"

