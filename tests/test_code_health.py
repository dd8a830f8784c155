"""Code health: imports point one way, files and functions stay short, ruff and mypy pass.

Static checks of the source tree (nothing is imported or run but the linters), so a change that adds an
import cycle, a 200-line function or a lint finding fails the test suite, and so CI, like a failing test.

Layers: ``nemsim`` (the library) never imports ``service`` or ``bench``; ``service`` never imports
``bench``; ``bench`` may import both. Units of the package graph: each subpackage or top-level module of
``nemsim`` (``nemsim.sim``, ``nemsim.cli``, ``nemsim.registry``, ...), ``service`` and ``bench``; no cycle
between units, and none between files either. Every import counts: module level, inside functions, under
``TYPE_CHECKING``, and ``importlib.import_module`` with a literal name; an import whose target is computed at
run time fails the test, since it could hide any edge. Importing ``a.b.c`` is an edge to the file of
``a.b.c`` only (the parent packages' ``__init__`` files run first, but re-exporting a package's own modules
from its ``__init__`` is not a cycle).
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
TOP = ("nemsim", "service", "bench")  # the project's packages
LAYERS = {"nemsim": set(), "service": {"nemsim"}, "bench": {"nemsim", "service"}}  # may import
MAX_FUNCTION_LINES = 120
MAX_CLI_FILE_LINES = 400
CLI_FILES = ("nemsim/cli.py", "nemsim/cli/**/*.py", "bench/cli/**/*.py", "service/cli.py")

Graph = dict[str, dict[str, list[str]]]  # {node: {imported node: ["file:line", ...]}}


def _sources() -> list[Path]:
    return sorted(p for top in TOP for p in (ROOT / top).rglob("*.py"))


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _unit(module: str) -> str:
    """The package-graph unit of a module: ``nemsim.<subpackage or module>``, else its top package."""
    parts = module.split(".")
    return ".".join(parts[:2]) if parts[0] == "nemsim" and len(parts) > 1 else parts[0]


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


def module_graph() -> Graph:
    """File-level import graph: {module: {imported project module: ["file:line", ...]}}."""
    graph: Graph = {}
    for path in _sources():
        src = _module_name(path)
        edges = graph.setdefault(src, {})
        for target, line in _imports(path):
            where = f"{path.relative_to(ROOT)}:{line}"
            if target.split(".")[0] in TOP and target != src and where not in edges.get(target, []):
                edges.setdefault(target, []).append(where)
    return graph


def package_graph() -> Graph:
    """The module graph collapsed onto units (``_unit``); edges inside a unit dropped."""
    graph: Graph = {}
    for src, edges in module_graph().items():
        out = graph.setdefault(_unit(src), {})
        for dst, where in edges.items():
            if _unit(dst) != _unit(src):
                out.setdefault(_unit(dst), []).extend(where)
    return graph


def _cycles(graph: Graph) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
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


def _cycle_report(graph: Graph) -> list[str]:
    problems = []
    for scc in _cycles(graph):
        lines = [f"  {a} -> {b}: {', '.join(graph[a][b])}" for a in scc for b in scc if b in graph.get(a, {})]
        problems.append(f"cycle between {', '.join(scc)}:\n" + "\n".join(lines))
    return problems


def layer_violations(graph: Graph) -> list[str]:
    """Edges from one top package to another that ``LAYERS`` does not allow."""
    bad = []
    for src, edges in sorted(graph.items()):
        for dst, where in sorted(edges.items()):
            a, b = src.split(".")[0], dst.split(".")[0]
            if a != b and b not in LAYERS[a]:
                bad.append(f"{src} -> {dst}: {', '.join(where)}")
    return bad


def test_no_cycle_between_packages():
    problems = _cycle_report(package_graph())
    assert not problems, "package dependencies must point one way\n" + "\n".join(problems)


def test_no_cycle_between_files():
    problems = _cycle_report(module_graph())
    assert not problems, "file imports must point one way\n" + "\n".join(problems)


def test_the_library_imports_neither_the_service_nor_the_bench():
    bad = layer_violations(module_graph())
    assert not bad, (
        "nemsim must not import service or bench, service must not import bench "
        "(register commands through the nemsim.cli entry points):\n" + "\n".join(bad)
    )


def _tree(tmp_path: Path, files: dict[str, str]) -> None:
    for rel, body in files.items():
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(body)
        for parent in path.relative_to(tmp_path).parents:
            if parent != Path(".") and not (tmp_path / parent / "__init__.py").exists():
                (tmp_path / parent / "__init__.py").write_text("")


def test_the_checks_see_function_level_and_importlib_imports(tmp_path, monkeypatch):
    """The checker itself: cycles hidden in a function body and behind import_module are found, between
    units and between files, and so are imports across the layers."""
    _tree(tmp_path, {
        "nemsim/a/x.py": "def f():\n    from nemsim.b.x import g\n    return g\n",
        "nemsim/b/x.py": "import importlib\n\ndef g():\n    return importlib.import_module('nemsim.a.x')\n",
        "nemsim/c/p.py": "from . import q\n",
        "nemsim/c/q.py": "if TYPE_CHECKING:\n    from nemsim.c.p import P\n",
        "nemsim/c/__init__.py": "from nemsim.c.p import q\n",  # a package re-exporting its modules: no cycle
        "nemsim/d.py": "def f():\n    import bench.tool\n",
        "service/app.py": "from nemsim.c import q\n",
        "bench/tool.py": "from service.app import q\n",
    })
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert _cycles(package_graph()) == [["nemsim.a", "nemsim.b"]]
    assert sorted(_cycles(module_graph())) == [["nemsim.a.x", "nemsim.b.x"], ["nemsim.c.p", "nemsim.c.q"]]
    assert [v.split(":")[0] for v in layer_violations(module_graph())] == ["nemsim.d -> bench.tool"]


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
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and not _is_numba_kernel(node):
                n = (node.end_lineno or node.lineno) - node.lineno + 1
                if n > limit:
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    return found


def test_no_function_over_120_lines():
    found = long_functions()
    assert not found, f"functions over {MAX_FUNCTION_LINES} lines (split them):\n" + "\n".join(found)


def test_no_cli_file_over_400_lines():
    """One module per command group, each short (nemsim/cli/, bench/cli/, service/cli.py)."""
    paths = sorted({p for pattern in CLI_FILES for p in ROOT.glob(pattern) if p.is_file()})
    sizes = {p: len(p.read_text().splitlines()) for p in paths}
    long = [f"{p.relative_to(ROOT)} ({n} lines)" for p, n in sizes.items() if n > MAX_CLI_FILE_LINES]
    assert not long, f"CLI files over {MAX_CLI_FILE_LINES} lines (split the group):\n" + "\n".join(long)


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
    res = subprocess.run([_tool("mypy"), *TOP], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def _is_module(dotted: str) -> bool:
    base = ROOT.joinpath(*dotted.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def test_project_imports_name_existing_modules():
    """Every ``import nemsim.x`` / ``from nemsim.x import y`` (function-level ones included, and the same
    for ``service`` and ``bench``) names a module that exists: a moved module cannot hide behind a lazy
    import that only runs on a rare path."""
    missing = []
    for path in [*_sources(), *sorted((ROOT / "tests").rglob("*.py"))]:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and not node.level and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            else:
                continue
            for name in names:
                if name.split(".")[0] in TOP and not _is_module(name):
                    missing.append(f"{path.relative_to(ROOT)}:{node.lineno} {name}")
    assert not missing, "imports of modules that do not exist:\n" + "\n".join(missing)
