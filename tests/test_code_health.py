"""Code health: package dependencies point one way, functions stay short, ruff and mypy pass.

Static checks of the source tree (nothing is imported or run but the linters), so a change that adds a
package cycle, a 200-line function or a lint finding fails the test suite, and so CI, like a failing test.

Units of the dependency graph: each subpackage of ``nemsim`` (``nemsim.sim``, ``nemsim.evaluation``, ...),
each top-level module (``nemsim.cli``, ``nemsim.registry``, ...) and the ``service`` package. Every import
counts: module level, inside functions, under ``TYPE_CHECKING``, and ``importlib.import_module`` with a
literal name; an import whose target is computed at run time fails the test, since it could hide any edge.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "nemsim"
MAX_FUNCTION_LINES = 120


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _unit(module: str) -> str:
    """The graph unit of a module: its ``nemsim`` subpackage or top-level module, else its package."""
    parts = module.split(".")
    return parts[1] if parts[0] == "nemsim" and len(parts) > 1 else parts[0]


def _resolve(name: str) -> str:
    """The deepest existing module of a dotted name (``nemsim.sim.SimConfig`` -> ``nemsim.sim``)."""
    parts = name.split(".")
    while parts:
        base = ROOT.joinpath(*parts)
        if base.with_suffix(".py").is_file() or (base / "__init__.py").is_file():
            return ".".join(parts)
        parts.pop()
    return name


def _imports(path: Path) -> Iterator[tuple[str, int]]:
    """(imported module, line) of every import in ``path``, function-level ones included."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield _resolve(alias.name), node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            for alias in node.names:
                yield _resolve(f"{source}.{alias.name}"), node.lineno
        elif isinstance(node, ast.Call):
            func = node.func
            fname = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            if fname in ("import_module", "__import__"):
                arg = node.args[0] if node.args else None
                if not (isinstance(arg, ast.Constant) and isinstance(arg.value, str)):
                    raise AssertionError(f"{path.relative_to(ROOT)}:{node.lineno}: import of a computed name")
                yield _resolve(arg.value), node.lineno


def package_graph() -> dict[str, dict[str, list[str]]]:
    """{unit: {imported unit: ["file:line", ...]}} over every module under nemsim/ and service/."""
    graph: dict[str, dict[str, list[str]]] = {}
    for path in sorted([*PACKAGE.rglob("*.py"), *(ROOT / "service").rglob("*.py")]):
        src = _unit(_module_name(path))
        edges = graph.setdefault(src, {})
        for target, line in _imports(path):
            if target.split(".")[0] not in ("nemsim", "service"):
                continue
            dst = _unit(target)
            if dst != src:
                edges.setdefault(dst, []).append(f"{path.relative_to(ROOT)}:{line}")
    return graph


def _cycles(graph: dict[str, dict[str, list[str]]]) -> list[list[str]]:
    """Strongly connected components with more than one unit (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            scc = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                scc.append(w)
                if w == v:
                    break
            if len(scc) > 1:
                out.append(sorted(scc))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_cycle_between_packages():
    graph = package_graph()
    problems = []
    for scc in _cycles(graph):
        lines = [f"  {a} -> {b}: {', '.join(graph[a][b])}" for a in scc for b in scc if b in graph.get(a, {})]
        problems.append(f"cycle between {', '.join(scc)}:\n" + "\n".join(lines))
    assert not problems, "package dependencies must point one way\n" + "\n".join(problems)


def test_only_the_cli_imports_the_service():
    users = {src for src, dsts in package_graph().items() if "service" in dsts}
    assert users <= {"cli"}, f"the library must not depend on the service: {sorted(users)}"


def test_the_cycle_check_sees_function_level_and_importlib_imports(tmp_path, monkeypatch):
    """The checker itself: a cycle hidden in a function body and behind import_module is found."""
    pkg = tmp_path / "nemsim"
    for sub, body in {
        "a": "def f():\n    from nemsim.b.x import g\n    return g\n",
        "b": "import importlib\n\ndef g():\n    return importlib.import_module('nemsim.a.x')\n",
    }.items():
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
        (pkg / sub / "x.py").write_text(body)
    (pkg / "__init__.py").write_text("")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", pkg)
    assert _cycles(package_graph()) == [["a", "b"]]


def _is_numba_kernel(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    for dec in fn.decorator_list:
        target = dec.func if isinstance(dec, ast.Call) else dec
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name in ("njit", "jit", "vectorize", "guvectorize"):
            return True
    return False


def long_functions(limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """Functions (methods and nested functions included) longer than ``limit`` lines, numba kernels aside."""
    found = []
    for path in sorted([*PACKAGE.rglob("*.py"), *(ROOT / "service").rglob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and not _is_numba_kernel(node):
                n = (node.end_lineno or node.lineno) - node.lineno + 1
                if n > limit:
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    return found


def test_no_function_over_120_lines():
    found = long_functions()
    assert not found, f"functions over {MAX_FUNCTION_LINES} lines (split them):\n" + "\n".join(found)


def _tool(name: str) -> str:
    """The linter next to this interpreter (the venv's), else on PATH; the test extra installs both."""
    exe = Path(sys.executable).with_name(name)
    path = str(exe) if exe.is_file() else shutil.which(name)
    if path is None:
        pytest.fail(f"{name} is not installed: pip install -e '.[test]'")
    return path


def test_ruff_clean():
    res = subprocess.run([_tool("ruff"), "check", "--no-cache", "."], cwd=ROOT, capture_output=True,
                         text=True)
    assert res.returncode == 0, res.stdout + res.stderr


@pytest.mark.slow
def test_mypy_clean():
    res = subprocess.run([_tool("mypy"), "nemsim", "service"], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def _is_module(dotted: str) -> bool:
    base = ROOT.joinpath(*dotted.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def test_project_imports_name_existing_modules():
    """Every ``import nemsim.x`` / ``from nemsim.x import y`` (function-level ones included) names a module
    that exists: a moved module cannot hide behind a lazy import that only runs on a rare path."""
    missing = []
    files = [*PACKAGE.rglob("*.py"), *(ROOT / "service").rglob("*.py"), *(ROOT / "tests").rglob("*.py")]
    for path in sorted(files):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and not node.level and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            else:
                continue
            for name in names:
                if name.split(".")[0] in ("nemsim", "service") and not _is_module(name):
                    missing.append(f"{path.relative_to(ROOT)}:{node.lineno} {name}")
    assert not missing, "imports of modules that do not exist:\n" + "\n".join(missing)
