"""The tree's layout (issues #16, #26): no import cycle in vergence/ or services/, not even through an import
inside a function; vergence/ never imports zenoh or the services; each package imports only what ALLOWED lets it
(a new arrow fails here); observers publish nothing of the pipeline's; the data path's stages (frames: capture
side, shards: worker side, gather: reducer side) each in a module of its own that imports none of the others;
the tests mirror the tree; docs/ARCHITECTURE.md names every module there is."""

from __future__ import annotations

import ast
import json
import pkgutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

import background
import sweeps
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
    """PROBE of module `name` in a fresh interpreter (sweeps.probe; done ahead in the background when the test below is
    selected, tests/background.py)."""
    return background.get(sweeps.probe, PROBE, name)


for _name in MODULES:
    background.ahead(sweeps.probe, PROBE, _name,
                     tests="test_every_module_imports_first_in_a_fresh_interpreter_without_zenoh_or_services")


@pytest.mark.slow
def test_every_module_imports_first_in_a_fresh_interpreter_without_zenoh_or_services():
    """Each module imported first, alone, in its own interpreter: an import cycle (a module importing a
    partly initialised one) fails here, whichever module the cycle is entered by."""
    assert {"vergence.network.params", "vergence.stages.frames", "vergence.stages.shards", "vergence.stages.gather",
            "vergence.network.decide", "vergence.network.match"} <= set(MODULES)
    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(_probe, MODULES))
    for name, rc, out, err in results:
        assert rc == 0, f"import {name} failed:\n{err[-2000:]}"
        got = json.loads(out.strip().splitlines()[-1])
        assert got.get("loaded", []) == [], f"import {name} loads {got['loaded']}"


@pytest.mark.slow
def test_the_processes_that_run_no_kernel_start_without_numba():
    """`vergence up`, the actuator and the clients load no numba (vergence's public names are imported on first use,
    and the settings need no kernel): about 0.6 s less of each start. `vergence.decide` and `vergence.match` stay
    the functions when their modules are imported."""
    import subprocess
    import sys

    code = ("import sys, services.ops.up, services.pipeline.actuator, services.clients.latency, "
            "services.clients.fixate, vergence.config, vergence.wire.keys, vergence.wire.messages\n"
            "print(sorted(m for m in ('numba', 'vergence.network.kernel', 'vergence.network.retina')\n"
            "             if m in sys.modules))\n"
            "import vergence, vergence.network.decide, vergence.network.match\n"
            "print(vergence.network.decide.__name__, type(vergence.decide).__name__, type(vergence.match).__name__)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split("\n")[:2] == ["[]", "vergence.network.decide function function"]


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


TREE = ROOT.parent
SERVICES = TREE / "services"
PACKAGES = ("vergence", "services")


def _modules() -> list[str]:
    """Every module of both import packages, by dotted name."""
    out = []
    for top in PACKAGES:
        base = TREE / top
        out += [".".join(p.relative_to(TREE).with_suffix("").parts).removesuffix(".__init__")
                for p in base.rglob("*.py") if "__pycache__" not in p.parts]
    return sorted(out)


def _path(name: str) -> Path:
    p = TREE.joinpath(*name.split("."))
    return p / "__init__.py" if p.is_dir() else p.with_suffix(".py")


def _graph(deferred: bool = True, names: list[str] | None = None) -> dict[str, set[str]]:
    graph = {}
    for name in names or MODULES:
        path = _path(name)
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        graph[name] = _imports(path, package, deferred)
    return graph


def _edges(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """Module -> the modules of the tree it imports (`from pkg import mod` names mod). A package's __init__
    importing its own submodules is the package's public API, and a module naming its own package finds it
    initialised already: neither is an arrow of the layout."""
    known = set(graph)
    edges = {m: {d for d in deps if d in known and d != m} for m, deps in graph.items()}
    return {m: {d for d in ds if not d.startswith(m + ".") and not m.startswith(d + ".")} for m, ds in edges.items()}


def _cycle(edges: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}

    def visit(m: str, trail: list[str]) -> list[str] | None:
        state[m] = 1
        for d in sorted(edges[m]):
            if state.get(d) == 1:
                return trail[trail.index(d):] + [m, d] if d in trail else trail + [m, d]
            if d not in state and (found := visit(d, trail + [m])):
                return found
        state[m] = 2
        return None

    for m in sorted(edges):
        if m not in state and (found := visit(m, [])):
            return found
    return None


def test_no_source_in_the_library_names_zenoh_or_the_services():
    for name, deps in _graph().items():
        bad = sorted(d for d in deps if d.split(".")[0] in FORBIDDEN)
        assert bad == [], f"{name} imports {bad}"


def test_no_import_cycle_anywhere_not_even_inside_a_function():
    """Over vergence/ and services/ both, the imports at a module's top and those deferred inside functions: a
    deferred import that closes a cycle is a cycle all the same (it only moves the failure to a call)."""
    edges = _edges(_graph(deferred=True, names=_modules()))
    assert _cycle(edges) is None, "import cycle: " + " -> ".join(_cycle(edges))


def test_a_cycle_inside_a_function_is_found():
    """The check above can fail: two modules importing each other, one of them inside a function."""
    edges = {"a": {"b"}, "b": {"a"}}
    assert _cycle(edges) == ["a", "b", "a"]
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    tree = ast.parse("def f():\n    from . import other\n")
    assert "vergence.other" in {d for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                                for d in [f"vergence.{node.names[0].name}"]}


def test_the_stages_stay_apart():
    edges = _edges(_graph(deferred=False))
    stages = {"vergence.stages.frames", "vergence.stages.shards", "vergence.stages.gather"}
    for s in stages:
        assert not (edges[s] & stages), f"{s} imports another stage: {sorted(edges[s] & stages)}"
    assert "vergence.network.params" in edges["vergence.network.decide"] and not edges["vergence.network.params"] & {
        "vergence.network.decide", "vergence.network.match"}  # Params in one place, below every user of it


# Who may import whom: each package of the tree and the packages of the tree it may import (itself always). The
# library imports nothing of the services; the runtime only the library; the pipeline, the observers and the
# bridges the runtime; the clients also the observers (replay --view shows the cockpit); the offline tools also the
# observers (sim --save) and ops' process launcher (the pipeline benchmarks start processes); ops, everything.
ALLOWED = {
    "vergence": set(),
    "services.runtime": {"vergence"},
    "services.pipeline": {"vergence", "services.runtime"},
    "services.observe": {"vergence", "services.runtime"},
    "services.bridges": {"vergence", "services.runtime"},
    "services.clients": {"vergence", "services.runtime", "services.observe"},
    "services.offline": {"vergence", "services.runtime", "services.observe", "services.ops"},
    "services.ops": {"vergence", "services.runtime"},
}


def _package(module: str) -> str:
    parts = module.split(".")
    return "vergence" if parts[0] == "vergence" else ".".join(parts[:2])


def test_every_package_imports_only_what_the_table_allows():
    assert sorted({_package(m) for m in _modules() if m != "services"}) == sorted(ALLOWED)
    for m, deps in _edges(_graph(deferred=True, names=_modules())).items():
        if m == "services":
            continue
        arrows = {_package(d) for d in deps} - {_package(m)}
        assert arrows <= ALLOWED[_package(m)], f"{m} imports {sorted(arrows - ALLOWED[_package(m)])}: a new arrow"


# what an observer may not say on the bus: a command, a fixation, a hold, or any of the pipeline's messages
COMMANDING = ("command", "fixate", "hold", "frame", "preview", "decision", "profile", "correlation", "motor_state",
              "workers")


def test_observers_never_publish_commands():
    """The observers (services/observe/) build no key of the pipeline's or the motor's: they subscribe through
    the runtime, which publishes only their status and liveliness."""
    for path in sorted((SERVICES / "observe").glob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                f = node.func
                if f.attr in ("put", "declare_publisher", "publisher", "publish"):
                    args = [a for a in node.args if isinstance(a, ast.Call) and isinstance(a.func, ast.Attribute)]
                    built = {a.func.attr for a in args
                             if isinstance(a.func.value, ast.Name) and a.func.value.id == "keys"}
                    assert not built & set(COMMANDING), f"{path.name}:{node.lineno} publishes {built}"
                    assert f.attr != "declare_publisher", f"{path.name}:{node.lineno} declares a publisher"


# The modules with no test file of their own, and where they are tested.
TESTED_ELSEWHERE = {
    "vergence.tools.bench": "tests/services/offline/test_bench.py (the benchmarks run from the CLI)",
    "vergence.head.control": "tests/scenarios/test_tracking.py (the controller in the closed loop)",
    "vergence.head.predict": "tests/scenarios/test_tracking.py (the predictors, and the controller that runs them)",
    "vergence.io.images": "tests/vergence/io/test_sources.py (read_image's errors, through the sources)",
    "vergence.network.params": "tests/vergence/network/test_decide.py, test_match.py (the parameters' effects)",
    "vergence.network.photometric": "tests/vergence/network/test_retina.py (the mapping through the retina's strips)",
    "vergence.ros2.node": "tests/services/bridges/test_ros2.py (real rclpy nodes)",
    "vergence.ros2.source": "tests/services/bridges/test_ros2.py (the ros2: source end to end)",
    "vergence.observe.screen": "tests/vergence/observe/test_monitor.py (the screen drawn from the model's snapshots)",
    "vergence.network.simd": "tests/vergence/network/test_kernel.py (the kernel's variants agree)",
    "vergence.head.lag": "tests/vergence/head/test_doubt.py (the lag fitted through the check's faults and probes)",
    "vergence.head.follows": "tests/vergence/head/test_doubt.py, test_calibrate.py (the verdict, through the check and "
                             "calibrate's refusals)",
}


def test_the_tests_mirror_the_tree():
    """tests/ holds the project-wide checks (and the check of the test run itself, test_split.py) and the shared
    helpers; tests/vergence/ and tests/services/ mirror the
    two packages folder by folder: a test file per library module (test_<module>.py; vergence/sim's and
    vergence/motors' in their folders), a test folder per services subpackage; tests/scenarios/ the tests of
    several processes or modules at once; tests/deploy/ the deployment's (deploy/). No test file names a module
    that does not exist, and no test folder is a package (pytest's importlib mode lets two folders hold a file of
    the same name)."""
    tests = Path(__file__).resolve().parent
    assert sorted(p.name for p in tests.glob("test_*.py")) == ["test_install.py", "test_layout.py", "test_lint.py",
                                                               "test_split.py"]
    places = {p.parent.relative_to(tests).as_posix() for p in tests.rglob("test_*.py")}
    folders = {p.parent.relative_to(TREE).as_posix() for top in PACKAGES for p in (TREE / top).rglob("__init__.py")}
    assert places == {".", "scenarios", "deploy"} | folders - {"services"}, places ^ folders
    for p in tests.rglob("test_*.py"):
        where = p.parent.relative_to(tests)
        if where.parts and where.parts[0] in PACKAGES and where.as_posix() not in ("vergence/sim", "vergence/motors"):
            module = TREE / where / (p.stem.removeprefix("test_") + ".py")
            assert module.is_file(), f"{p.relative_to(tests)} mirrors no module ({module.relative_to(TREE)})"
    library = [m for m in _modules() if m.startswith("vergence.") and _path(m).name != "__init__.py"
               and m.split(".")[1] not in ("sim", "motors")]
    mirror = {m: tests / _path(m).relative_to(TREE).parent / f"test_{_path(m).stem}.py" for m in library}
    missing = [m for m in library if m not in TESTED_ELSEWHERE and not mirror[m].is_file()]
    assert missing == [], f"library modules with no test file: {missing}"
    assert not [m for m in TESTED_ELSEWHERE if m not in library], "TESTED_ELSEWHERE names a module that is not there"
    assert not [p for p in tests.rglob("__init__.py") if p.parent.name != "emulators"]


MAX_TOP_MODULES = 10


def test_the_library_top_holds_at_most_10_modules():
    """vergence/ by concept (issue #34): the network, the head, the wire, the stages, io, ros2, sim, motors,
    observe, tools are folders; at most 10 modules stay at the top (the settings and what every folder shares)."""
    top = sorted(p.stem for p in ROOT.glob("*.py") if p.name != "__init__.py")
    assert len(top) <= MAX_TOP_MODULES, top
    folders = sorted(p.parent.name for p in ROOT.glob("*/__init__.py"))
    assert folders == ["head", "io", "motors", "network", "observe", "ros2", "sim", "stages", "tools", "wire"]


MAX_FUNCTION_LINES = 80


def _long_functions(source: str) -> list[tuple[str, int]]:
    tree = ast.parse(source)
    lengths = [(n.name, n.end_lineno - n.lineno + 1) for n in ast.walk(tree)
               if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
    return [(name, n) for name, n in lengths if n > MAX_FUNCTION_LINES]


def test_no_function_in_the_product_is_over_80_lines():
    """A process's main reads as a few named steps: no function of vergence/ or services/ is longer than 80 lines
    (a process's state lives in a class with named methods, not in closures of one main)."""
    long = {f"{m} {name}": n for m in _modules() for name, n in _long_functions(_path(m).read_text())}
    assert long == {}
    assert _long_functions("def f():\n" + "    x = 1\n" * 80) == [("f", 81)]  # the check can fail


MAX_MODULE_LINES = 450


def test_no_module_in_the_product_is_over_450_lines():
    """A module holds one concept (issue #34): none of vergence/ or services/ is longer than 450 lines."""
    long = {m: n for m in _modules() if (n := len(_path(m).read_text().splitlines())) > MAX_MODULE_LINES}
    assert long == {}

def _resolve(dotted: str):
    """The object a dotted name of the docs names: its longest importable module, then attributes."""
    import importlib

    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for name in parts[i:]:
            obj = getattr(obj, name)
        return obj
    raise ModuleNotFoundError(dotted)


def test_every_name_the_library_doc_gives_is_importable_there():
    """docs/LIBRARY.md cannot name what is not there (issue #34): each vergence.X.Y it writes resolves (a module,
    then its attributes), and `from vergence import ...` takes every public name vergence's __init__ lists."""
    import re

    import vergence

    text = (TREE / "docs" / "LIBRARY.md").read_text()
    names = sorted(set(re.findall(r"vergence(?:\.[A-Za-z_][A-Za-z_0-9]*)+", text)))
    assert len(names) >= 10
    missing = []
    for name in names:
        try:
            _resolve(name)
        except (ImportError, AttributeError):
            missing.append(name)
    assert missing == []
    assert all(getattr(vergence, n) is not None for n in vergence.__all__)
    assert callable(vergence.decide) and callable(vergence.match)
    with pytest.raises(AttributeError):
        _resolve("vergence.network.retina.no_such_name")

DOCS = TREE / "docs"
README = TREE / "README.md"
# a path of the tree as docs/ARCHITECTURE.md names it: in backticks, starting at a top-level folder or file
_NAMED = r"`((?:vergence|services|tests|deploy|docs|\.ci)/[^`\s]*|[A-Za-z_.-]+\.(?:py|md|yml|toml)|Dockerfile)`"


def test_architecture_doc_names_every_module_and_only_real_paths():
    """docs/ARCHITECTURE.md cannot go stale: every module file of vergence/ and services/ (but __init__.py), as
    the tree has them when the test runs, is named in it by its path, and every path it names exists."""
    import re

    text = (DOCS / "ARCHITECTURE.md").read_text()
    named = set(re.findall(_NAMED, text))
    modules = sorted(p.relative_to(TREE).as_posix() for top in PACKAGES for p in (TREE / top).rglob("*.py")
                     if p.name != "__init__.py" and "__pycache__" not in p.parts)
    missing = [m for m in modules if m not in named]
    assert missing == [], f"docs/ARCHITECTURE.md does not name {missing}: add a row to its folder's table"
    gone = sorted(n for n in named if not (TREE / n.split("::")[0].rstrip("/")).exists())
    assert gone == [], f"docs/ARCHITECTURE.md names {gone}, not in the tree"


def test_readme_is_short_and_draws_the_data_path():
    lines = README.read_text().splitlines()
    assert len(lines) <= 300, f"README.md is {len(lines)} lines (at most 300: the rest belongs in docs/)"
    assert "```mermaid" in lines, "README.md has no ```mermaid block (the data path)"


def test_relative_links_in_readme_and_docs_resolve():
    import re

    bad = []
    for doc in [README, *sorted(DOCS.glob("*.md"))]:
        for target in re.findall(r"\]\(([^)\s]+)\)", doc.read_text()):
            path = target.split("#")[0]
            if not path or re.match(r"[a-z]+:", path):
                continue
            if not (doc.parent / path).exists():
                bad.append(f"{doc.relative_to(TREE)}: {target}")
    assert bad == [], f"broken links: {bad}"
