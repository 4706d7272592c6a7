"""The library's layout (issue #16): no import cycle, vergence/ never imports zenoh or the services, and the
data path's stages (frames: capture side, shards: worker side, gather: reducer side) each in a module of its
own that imports none of the others."""

from __future__ import annotations

import ast
import json
import pkgutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

import vergence

ROOT = Path(vergence.__file__).resolve().parent
MODULES = sorted(m.name for m in pkgutil.walk_packages([str(ROOT)], "vergence."))
FORBIDDEN = ("zenoh", "vergence_services")

PROBE = """
import importlib, json, sys
name = sys.argv[1]
try:
    importlib.import_module(name)
except ModuleNotFoundError as e:  # an optional third-party package not installed here: not the layout's concern
    if (e.name or "").split(".")[0] in ("vergence", "vergence_services", "zenoh"):
        raise
    print(json.dumps({"skipped": e.name}))
    sys.exit(0)
print(json.dumps({"loaded": sorted(m for m in sys.modules if m.split(".")[0] in %r)}))
""" % (FORBIDDEN,)


def _probe(name: str) -> tuple[str, int, str, str]:
    r = subprocess.run([sys.executable, "-c", PROBE, name], capture_output=True, text=True, timeout=120)
    return name, r.returncode, r.stdout, r.stderr


@pytest.mark.slow
def test_every_module_imports_first_in_a_fresh_interpreter_without_zenoh_or_services():
    """Each module imported first, alone, in its own interpreter: an import cycle (a module importing a
    partly initialised one) fails here, whichever module the cycle is entered by."""
    assert {"vergence.params", "vergence.frames", "vergence.shards", "vergence.gather", "vergence.decide",
            "vergence.match"} <= set(MODULES)
    assert "vergence.pipeline" not in MODULES
    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(_probe, MODULES))
    for name, rc, out, err in results:
        assert rc == 0, f"import {name} failed:\n{err[-2000:]}"
        got = json.loads(out.strip().splitlines()[-1])
        assert got.get("loaded", []) == [], f"import {name} loads {got['loaded']}"


def _top_level(tree: ast.Module):
    """The statements run when the module is imported (not those inside functions or classes' methods)."""
    todo = list(tree.body)
    while todo:
        node = todo.pop()
        yield node
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            todo.extend(c for c in ast.iter_child_nodes(node) if isinstance(c, ast.stmt))


def _imports(path: Path, package: str, deferred: bool = True) -> set[str]:
    """The absolute names of the modules a source file imports (relative imports resolved), with those inside
    functions (deferred) or without."""
    out = set()
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree) if deferred else _top_level(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)  # `from . import kernel` names a module
    return out


def _graph(deferred: bool = True) -> dict[str, set[str]]:
    graph = {}
    for name in MODULES:
        mod_path = ROOT.joinpath(*name.split(".")[1:])
        path = mod_path / "__init__.py" if mod_path.is_dir() else mod_path.with_suffix(".py")
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        graph[name] = _imports(path, package, deferred)
    return graph


def test_no_source_in_the_library_names_zenoh_or_the_services():
    for name, deps in _graph().items():
        bad = sorted(d for d in deps if d.split(".")[0] in FORBIDDEN)
        assert bad == [], f"{name} imports {bad}"


def test_module_graph_has_no_cycle_and_stages_stay_apart():
    """Imports run at import time only: a deferred one inside a function (e.g. vergence.sim.rig's Rig.from_spec
    naming vergence.sim.moving) cannot fail an import."""
    graph = _graph(deferred=False)
    known = set(graph)
    edges = {m: {d for d in deps if d in known and d != m} for m, deps in graph.items()}
    # a package's __init__ importing its own submodules is the package's public API, and a module naming its
    # own package (`from . import kernel`) finds it initialised already: neither is a cycle of the layout
    for m in edges:
        edges[m] = {d for d in edges[m] if not d.startswith(m + ".") and not m.startswith(d + ".")}
    state: dict[str, int] = {}

    def visit(m: str, trail: list[str]) -> None:
        state[m] = 1
        for d in sorted(edges[m]):
            if state.get(d) == 1:
                raise AssertionError("import cycle: " + " -> ".join(trail[trail.index(d):] + [m, d]))
            if d not in state:
                visit(d, trail + [m])
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m, [])
    stages = {"vergence.frames", "vergence.shards", "vergence.gather"}
    for s in stages:
        assert not (edges[s] & stages), f"{s} imports another stage: {sorted(edges[s] & stages)}"
    assert "vergence.params" in edges["vergence.decide"] and not edges["vergence.params"] & {
        "vergence.decide", "vergence.match"}  # Params in one place, below every user of it


def test_the_tests_mirror_the_tree():
    """tests/ holds the project-wide checks and the shared helpers; tests/vergence/ the library's tests, its
    folders those of vergence/ (motors/, sim/); tests/services/ the services'. No test folder is a package
    (pytest's importlib mode lets two folders hold a file of the same name), and no test file sits elsewhere."""
    tests = Path(__file__).resolve().parent
    assert sorted(p.name for p in tests.glob("test_*.py")) == ["test_install.py", "test_layout.py", "test_lint.py"]
    places = {p.parent.relative_to(tests).as_posix() for p in tests.rglob("test_*.py")}
    subpackages = {p.parent.relative_to(ROOT).as_posix() for p in ROOT.glob("*/__init__.py")}
    assert places <= {".", "vergence", "services"} | {f"vergence/{s}" for s in subpackages}, places
    assert {"vergence", "services"} <= places
    assert not [p for p in tests.rglob("__init__.py") if p.parent.name != "emulators"]
