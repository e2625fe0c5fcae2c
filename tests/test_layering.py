"""The package's layering, checked from its source: who may import what.

- Only ``psdbake/usd/`` imports ``pxr``: USD stays at the edge, the numerics are testable
  without it. And not only directly: importing the pure modules (``PURE``: the psd: model,
  settings, results, farm planning, the OBJ format) in a fresh interpreter loads no ``pxr``
  at all, so a third party can evaluate the weights formula without usd-core.
- No import cycles between psdbake's modules, counting imports inside functions too (a cycle
  held together by a function-level import is still a cycle); only ``if TYPE_CHECKING:``
  blocks are left out, since they never run.
- Nothing in the package imports the CLI (it is a thin shell over the library), except the
  entry points that start it.
"""

from __future__ import annotations

import ast
import os

import pytest
from conftest import ROOT

PACKAGE = os.path.join(ROOT, "psdbake")
ENTRY_POINTS = {"psdbake.__main__", "psdbake._entry"}


def _modules() -> dict[str, str]:
    """module name -> file, for every module of the package."""
    found = {}
    for here, dirs, files in os.walk(PACKAGE):
        dirs[:] = [d for d in dirs if d != "__pycache__"]
        for name in files:
            if name.endswith(".py"):
                rel = os.path.relpath(os.path.join(here, name), ROOT)[:-3].replace(os.sep, ".")
                found[rel.removesuffix(".__init__")] = os.path.join(here, name)
    return found


MODULES = _modules()


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(module: str, path: str) -> list[tuple[str, int]]:
    """(imported module, line) for every import that can run, resolved to package modules
    where it names one (``from .usd import write`` -> psdbake.usd.write)."""
    package = module if path.endswith("__init__.py") else module.rpartition(".")[0]
    out: list[tuple[str, int]] = []

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child):
                for other in child.orelse:
                    visit(other)
                continue
            if isinstance(child, ast.Import):
                out.extend((alias.name, child.lineno) for alias in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    parts = package.split(".")
                    parts = parts[: len(parts) - (child.level - 1)]
                    base = ".".join(parts + ([child.module] if child.module else []))
                for alias in child.names:
                    full = f"{base}.{alias.name}"
                    out.append((full if full in MODULES else base, child.lineno))
            visit(child)

    with open(path, encoding="utf-8") as fh:
        visit(ast.parse(fh.read(), path))
    return out


GRAPH = {m: _imports(m, p) for m, p in MODULES.items()}


def test_only_psdbake_usd_imports_pxr():
    offenders = [f"{MODULES[m]}:{line} imports {target}" for m, edges in GRAPH.items()
                 if not m.startswith("psdbake.usd") for target, line in edges if target.split(".")[0] == "pxr"]
    assert not offenders, "\n".join(offenders)


#: Modules (and packages, every module under them) that must not load pxr, even transitively.
PURE = ("psdbake.model", "psdbake.settings", "psdbake.results", "psdbake.errors", "psdbake.tolerances",
        "psdbake.names", "psdbake.lookup", "psdbake.shot.frames", "psdbake.farm.plan", "psdbake.farm.jobs",
        "psdbake.sculpting.obj", "psdbake.fitting.regions", "psdbake.solver.powell", "psdbake.solver.inverse",
        "psdbake.export.blender.compiler", "psdbake.outputs", "psdbake.atomic")


def test_the_pure_modules_load_no_pxr_transitively():
    import subprocess
    import sys

    wanted = sorted(m for m in MODULES if any(m == p or m.startswith(p + ".") for p in PURE))
    code = ("import importlib, sys\n"
            f"for m in {wanted!r}:\n"
            "    importlib.import_module(m)\n"
            "    assert 'pxr' not in sys.modules, m\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert len(wanted) >= 20  # the model and its neighbours are all here


def test_registries_are_keyed_by_their_names():
    """A registry is a dictionary keyed by the literal names the CLI offers (names.py), so
    reordering one table can never rebind an entry to another name."""
    from psdbake import names
    from psdbake.model.posespace import POSE_SPACES
    from psdbake.model.rbf import KERNELS
    from psdbake.usd.write import FORMATS

    assert tuple(POSE_SPACES) == names.POSE_SPACE_NAMES
    assert tuple(KERNELS) == names.KERNEL_NAMES
    assert tuple(FORMATS) == names.LAYER_FORMATS


#: The layers, lowest first: a module imports only from its own layer or lower ones. The tree
#: reads as the pipeline: read USD -> pose space -> black-box skinning -> inverse -> RBF -> write.
LAYERS = (
    ("base", ("reproducible", "errors", "names", "tolerances", "arrays", "lookup", "outputs", "atomic", "paths")),
    ("model", ("model",)),
    ("geometry", ("normals", "deformers")),
    ("usd", ("usd",)),
    ("solver", ("solver", "delta_mush")),
    ("data", ("settings", "results")),
    ("stages", ("fitting", "shot", "mirroring", "sculpting")),
    ("clients", ("export",)),
    ("api", ("api",)),
    ("report", ("report",)),
    ("farm", ("farm",)),
    ("shell", ("console", "cli", "_entry", "__main__")),
)
#: The imports that point up, each for a reason (docs/contributing.md):
UPWARD = {
    ("psdbake.farm.job", "psdbake._entry"),  # a farm task is the psdbake command in a process of its own
    ("psdbake.outputs", "psdbake.usd.provenance"),  # an existing layer's kind is read with USD, lazily
    ("psdbake.usd.meshfaces", "psdbake.sculpting.obj.faces"),  # USD's faces read into the OBJ format's class
    ("psdbake.deformers", "psdbake.usd.diagnostics"),  # a deformer's USD error in USD's words, lazily
}


def _layer(module: str) -> int:
    top = module.split(".")[1]
    return next(i for i, (_, members) in enumerate(LAYERS) if top in members)


def test_imports_point_down_the_layers():
    """Every module (the public facade psdbake/__init__.py aside) imports from its own layer or
    lower ones, but for the few ``UPWARD`` imports, each with its reason."""
    up = {(m, t) for m, edges in GRAPH.items() if m != "psdbake" and "rig_script" not in m
          for t, _ in edges if t in MODULES and t != "psdbake" and t != m and _layer(t) > _layer(m)}
    assert up == UPWARD, f"imports pointing up the layers: {sorted(up - UPWARD)}; gone: {sorted(UPWARD - up)}"


def test_the_cli_is_imported_by_no_library_module():
    offenders = [f"{MODULES[m]}:{line}" for m, edges in GRAPH.items() if m not in ENTRY_POINTS
                 for target, line in edges if target == "psdbake.cli"]
    assert not offenders, "psdbake.cli is imported by: " + ", ".join(offenders)


def _cycles() -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    edges = {m: sorted({t for t, _ in GRAPH[m] if t in MODULES and t != m}) for m in MODULES}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges[v]:
            if w not in index:
                strong(w)
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
                found.append(sorted(component))

    for v in sorted(MODULES):
        if v not in index:
            strong(v)
    return found


def test_no_import_cycles():
    assert not _cycles(), f"import cycles: {_cycles()}"


def test_the_checks_see_the_package():
    """The checks above are only as good as the graph: it must hold the pipeline's modules and
    resolve relative imports to them (a parser regression would make every check pass)."""
    assert {"psdbake.api", "psdbake.cli", "psdbake.usd.read", "psdbake.usd.blackbox", "psdbake.solver.powell"} <= set(MODULES)
    assert "psdbake.api" in {t for t, _ in GRAPH["psdbake.cli"]}
    assert "psdbake.usd.read" in {t for t, _ in GRAPH["psdbake.api"]}
    assert any(t.startswith("pxr") for t, _ in GRAPH["psdbake.usd.read"])


def test_one_public_surface():
    """``psdbake.__all__`` is the one export list: every name resolves to the object its
    module defines, and the eager imports type checkers read name exactly the same set."""
    import psdbake

    for name in psdbake.__all__:
        assert getattr(psdbake, name) is not None, name
    with open(os.path.join(PACKAGE, "__init__.py"), encoding="utf-8") as fh:
        tree = ast.parse(fh.read())
    eager = {alias.asname or alias.name for node in ast.walk(tree) if isinstance(node, ast.If) and _is_type_checking(node)
             for stmt in node.body if isinstance(stmt, ast.ImportFrom) for alias in stmt.names}
    assert eager == set(psdbake.__all__) - {"__version__"}


def test_api_and_the_package_export_the_same_pipeline():
    """``psdbake.api.__all__`` and the names psdbake re-exports from it are one list."""
    import psdbake
    import psdbake.api

    assert set(psdbake.api.__all__) == set(psdbake._EXPORTS["api"])


def test_no_public_name_is_also_a_submodule():
    """``psdbake.evaluate`` and ``psdbake.mirror`` once named both api functions and modules of
    the package: importing the module (api does, on first use) rebinds the package attribute,
    so ``psdbake.evaluate(...)`` after ``psdbake.fit(...)`` called a module. A public name must
    never be a submodule's name."""
    import psdbake

    submodules = {name.split(".")[1] for name in MODULES if name.count(".") >= 1}
    assert not submodules & set(psdbake.__all__)


@pytest.mark.slow
def test_the_public_functions_stay_functions_after_every_module_loads():
    """In a fresh interpreter: every public name, read after the whole package is imported,
    is what its defining module says (a function, not a module of the same name)."""
    import subprocess
    import sys

    code = (
        "import importlib, types, psdbake\n"
        "first = {n: getattr(psdbake, n) for n in psdbake.__all__}\n"
        f"for m in {sorted(MODULES)!r}:\n"
        "    if 'blender' not in m and not m.endswith('__main__'): importlib.import_module(m)\n"
        "after = {n: getattr(psdbake, n) for n in psdbake.__all__}\n"
        "bad = [n for n in first if first[n] is not after[n] or isinstance(after[n], types.ModuleType)]\n"
        "assert not bad, bad\n"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
