"""The package's import graph has no cycle and no import up its layers, and `matspray --help` starts fast (imports no
torch).

The graph is read from the source with `ast`: every `import` / `from ... import` of the package's own
modules, at module level or inside functions (relative imports resolved). Importing a.b.c also runs
the `__init__` of a and a.b, so an edge to a module is also an edge to each package above it (except
the importer's own packages, which Python has already started when the importer runs).
"""

from __future__ import annotations

import ast
import subprocess
import sys
import time
from pathlib import Path

import matspray

PACKAGE_ROOT = Path(matspray.__file__).resolve().parent


def module_names(root: Path) -> dict[str, Path]:
    """Dotted module name -> source file, for every .py file of the package at `root`."""
    modules = {}
    for path in sorted(root.rglob("*.py")):
        parts = (root.name, *path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


def ancestors(name: str) -> list[str]:  # "a.b.c" -> ["a", "a.b"]
    parts = name.split(".")
    return [".".join(parts[:k]) for k in range(1, len(parts))]


def imported_modules(name: str, path: Path, modules: dict[str, Path]) -> list[tuple[str, int]]:
    """(module of the package, line) for every import statement in the file, wherever it is."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from . import x, from ..y import z
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module
            # `from p import x` imports the submodule p.x when there is one, else a name defined in p
            targets = [
                f"{source}.{alias.name}" if f"{source}.{alias.name}" in modules else source for alias in node.names
            ]
        else:
            continue
        for target in targets:
            while target not in modules and "." in target:  # `import a.b.c` of a name that is not a module
                target = target.rpartition(".")[0]
            if target in modules:
                found.append((target, node.lineno))
    return sorted(found, key=lambda hit: hit[1])


def import_graph(root: Path) -> dict[str, dict[str, str]]:
    """module -> {imported module: "file:line" of the first import statement that causes the edge}."""
    modules = module_names(root)
    graph: dict[str, dict[str, str]] = {name: {} for name in modules}
    for name, path in modules.items():
        own_packages = {name, *ancestors(name)}
        for target, line in imported_modules(name, path, modules):
            where = f"{path.relative_to(root.parent)}:{line}"
            for module in [*ancestors(target), target]:
                implicit = module != target
                if module in modules and not (implicit and module in own_packages) and module != name:
                    graph[name].setdefault(module, where)
    return graph


def find_cycles(graph: dict[str, dict[str, str]]) -> list[tuple[list[str], list[str]]]:
    """Per strongly connected component with more than one module (Tarjan): its modules, sorted, and
    the shortest cycle through the first of them."""
    index, low, stack, on_stack, components = {}, {}, [], set(), []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                connect(w)
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
                components.append(set(component))

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10 * len(graph)))
    try:
        for v in sorted(graph):
            if v not in index:
                connect(v)
    finally:
        sys.setrecursionlimit(limit)
    return [(sorted(component), shortest_cycle(graph, component)) for component in components]


def shortest_cycle(graph: dict[str, dict[str, str]], component: set[str]) -> list[str]:
    """The shortest cycle through the component's first module (breadth first): [m0, m1, ..., m0]."""
    start = min(component)
    parents, frontier = {start: None}, [start]
    while frontier:
        following = []
        for v in frontier:
            for w in sorted(graph[v]):
                if w == start:
                    path = [v]
                    while parents[path[-1]] is not None:
                        path.append(parents[path[-1]])
                    return [*reversed(path), start]
                if w in component and w not in parents:
                    parents[w] = v
                    following.append(w)
        frontier = following
    raise AssertionError(f"no cycle through {start}")  # unreachable for a strongly connected component


def describe(graph: dict[str, dict[str, str]], cycle: list[str]) -> str:
    return "\n".join(f"  {a} -> {b}  ({graph[a][b]})" for a, b in zip(cycle, cycle[1:]))


def test_the_package_has_no_import_cycle():
    graph = import_graph(PACKAGE_ROOT)
    assert len(graph) > 50 and sum(len(edges) for edges in graph.values()) > 100  # the whole package was read
    cycles = find_cycles(graph)
    report = "\n".join(
        f"cycle {k + 1} (its tangle: {', '.join(tangle)}):\n{describe(graph, cycle)}"
        for k, (tangle, cycle) in enumerate(cycles)
    )
    print(report or "no import cycle")
    assert not cycles, f"{len(cycles)} import cycle(s) in matspray:\n{report}"


# The layers of the package, bottom up: a module imports only from its own layer or those below. The tree reads as the
# paper: the data and the renderer, the 2D prior and the Gaussians, the method, then what uses the asset.
PLUMBING = (
    "matspray",
    "errors",
    "files",
    "presets",
    "device",
    "gaussians",
    "material",
    "metrics",
    "memory",
    "rundir",
    "settings",
)
LAYERS = (
    PLUMBING,
    ("data",),
    ("render",),
    ("gltf",),
    ("synth",),
    ("predictors",),
    ("geometry",),
    ("method",),
    ("export",),
    ("web",),
    ("view",),
    ("eval",),
    ("batch",),
    ("cli",),
    ("__main__",),
)
BENCHMARKS_ROOT = PACKAGE_ROOT.parent / "benchmarks"


def component(module: str) -> str:  # "matspray.method.refine.loop" -> "method"; "matspray" -> "matspray"
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


# render/'s own layers: what every part shares (its top-level modules), the rays lifting traces, the compiled CPU
# backend of both, the rasterizer's dispatch (which calls that backend), and shading on top
RENDER_LAYERS = (("",), ("rays",), ("numba",), ("raster",), ("shade",))


def render_part(module: str) -> str:  # "matspray.render.numba.backend" -> "numba"; "matspray.render.pairs" -> ""
    parts = module.split(".")
    return parts[2] if len(parts) > 2 and (PACKAGE_ROOT / "render" / parts[2]).is_dir() else ""


def upward_imports(graph: dict[str, dict[str, str]], layers=LAYERS, part=component) -> list[str]:
    """Every edge from a module to one of a higher layer, as "a -> b (file:line)"; `part` names a module's layer."""
    rank = {name: k for k, names in enumerate(layers) for name in names}
    return [
        f"{a} -> {b} ({where})"
        for a, edges in sorted(graph.items())
        for b, where in sorted(edges.items())
        if rank[part(b)] > rank[part(a)]
    ]


def test_every_top_level_module_and_package_has_a_layer():
    placed = {name for names in LAYERS for name in names}
    found = {component(name) for name in import_graph(PACKAGE_ROOT)}
    assert found - placed == set(), f"place these in LAYERS: {sorted(found - placed)}"
    assert placed - found == set(), f"LAYERS names what is gone: {sorted(placed - found)}"


def test_no_module_imports_up_the_layers():
    graph = import_graph(PACKAGE_ROOT)
    upward = upward_imports(graph)
    assert not upward, "imports up the layers (move the shared part down):\n" + "\n".join(upward)
    render = {
        a: {b: where for b, where in edges.items() if b.startswith("matspray.render.")}
        for a, edges in graph.items()
        if a.startswith("matspray.render.")
    }
    assert {render_part(m) for m in render} == {name for names in RENDER_LAYERS for name in names}
    upward = upward_imports(render, RENDER_LAYERS, render_part)
    assert not upward, "imports up render's layers:\n" + "\n".join(upward)


def test_the_benchmarks_have_no_import_cycle_and_the_library_never_imports_them():
    graph = import_graph(BENCHMARKS_ROOT)
    assert len(graph) > 20
    cycles = find_cycles(graph)
    assert not cycles, "\n".join(describe(graph, cycle) for _, cycle in cycles)
    library = [
        f"{path.relative_to(PACKAGE_ROOT.parent)}:{node.lineno}"
        for path in sorted(PACKAGE_ROOT.rglob("*.py"))
        for node in ast.walk(ast.parse(path.read_text(), str(path)))
        if (isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "benchmarks")
        or (isinstance(node, ast.Import) and any(alias.name.split(".")[0] == "benchmarks" for alias in node.names))
    ]
    assert not library, f"the library imports the benchmarks: {library}"


MAX_MODULES = 12


def test_no_package_folder_holds_more_than_12_modules():
    counts = {
        str(folder.relative_to(PACKAGE_ROOT)): sum(1 for p in folder.glob("*.py") if p.name != "__init__.py")
        for folder in [PACKAGE_ROOT, *(p.parent for p in PACKAGE_ROOT.rglob("*/__init__.py"))]
    }
    counts.pop(".")  # the top level: plumbing and the data model (the layers' first row)
    over = {name: n for name, n in counts.items() if n > MAX_MODULES}
    assert not over, f"package folders over {MAX_MODULES} modules: {over}"


MAX_FUNCTION_LINES = 80


def compiled(function: ast.FunctionDef) -> bool:
    """A compiled kernel: decorated with numba's `njit` (or the package's wrapper of it) or `cuda.jit`."""
    for decorator in function.decorator_list:
        target = decorator.func if isinstance(decorator, ast.Call) else decorator
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name in ("njit", "jit"):
            return True
    return False


def test_no_function_outside_the_compiled_kernels_is_over_80_lines():
    long = [
        f"{path.relative_to(PACKAGE_ROOT.parent)}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for path in sorted(PACKAGE_ROOT.rglob("*.py"))
        for node in ast.walk(ast.parse(path.read_text(), str(path)))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES
        and not compiled(node)
    ]
    assert not long, "functions over 80 lines (split them):\n" + "\n".join(long)


def test_the_layer_check_finds_an_import_up(tmp_path):
    """The checker itself: a function-local import from a low layer into a high one is found, with its line; imports
    down and within a layer are not."""
    root = write_package(
        tmp_path,
        {
            "pkg/__init__.py": "",
            "pkg/errors.py": "",
            "pkg/data/__init__.py": "",
            "pkg/data/read.py": "from pkg.errors import x\ndef f():\n    from pkg.method.run import g\n",
            "pkg/method/__init__.py": "",
            "pkg/method/run.py": "from pkg.data.read import f\nfrom pkg.method import other\n",
            "pkg/method/other.py": "",
        },
    )
    layers = (("pkg", "errors"), ("data",), ("method",))
    assert upward_imports(import_graph(root), layers) == [
        "pkg.data.read -> pkg.method (pkg/data/read.py:3)",
        "pkg.data.read -> pkg.method.run (pkg/data/read.py:3)",
    ]


def write_package(root: Path, files: dict[str, str]) -> Path:
    for relative, text in files.items():
        path = root / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root / "pkg"


def test_finds_cycles_through_local_relative_and_package_imports(tmp_path):
    """The checker itself: a function-local relative import closing a loop, and a loop that only exists
    because a package's __init__ re-exports a module that imports back into it."""
    root = write_package(
        tmp_path,
        {
            "pkg/__init__.py": "",
            "pkg/a.py": "import json\nfrom pkg.b import f\n",
            "pkg/b.py": "def f():\n    from .sub import c\n",
            "pkg/sub/__init__.py": "",
            "pkg/sub/c.py": "from .. import a\n",
            "pkg/lib/__init__.py": "from pkg.lib.x import X\n",
            "pkg/lib/x.py": "from ..uses import helper\nX = 1\n",
            "pkg/lib/y.py": "Y = 2\n",
            "pkg/uses.py": "from pkg.lib.y import Y\ndef helper():\n    return Y\n",
            "pkg/clean.py": "from pkg.lib import X\nfrom pkg.sub.c import a\nimport pkg.lib.x.X\n",
        },
    )
    graph = import_graph(root)
    assert graph["pkg.clean"] == {
        "pkg.lib": "pkg/clean.py:1",
        "pkg.sub": "pkg/clean.py:2",
        "pkg.sub.c": "pkg/clean.py:2",
        "pkg.lib.x": "pkg/clean.py:3",
    }
    assert graph["pkg.sub.c"] == {"pkg.a": "pkg/sub/c.py:1"}  # pkg itself is already importing when c runs
    cycles = sorted(cycle for _, cycle in find_cycles(graph))
    assert cycles == [["pkg.a", "pkg.b", "pkg.sub.c", "pkg.a"], ["pkg.lib", "pkg.lib.x", "pkg.uses", "pkg.lib"]]
    assert "pkg.b -> pkg.sub.c  (pkg/b.py:2)" in describe(graph, cycles[0])
    assert "pkg.uses -> pkg.lib  (pkg/uses.py:1)" in describe(graph, cycles[1])  # through pkg/lib/__init__.py


def test_help_is_fast_and_imports_no_torch():
    """`python -m matspray --help` builds every subcommand's parser; the library (torch) loads only
    when a command runs."""
    command = [sys.executable, "-m", "matspray", "--help"]
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, cwd=PACKAGE_ROOT.parent, timeout=60)
    elapsed = time.perf_counter() - started
    print(f"python -m matspray --help: {elapsed:.2f} s wall")
    assert done.returncode == 0 and "usage: matspray" in done.stdout, done.stderr
    assert elapsed < 3.0, f"`matspray --help` took {elapsed:.2f} s (goal: under 1 s)"
    probe = (
        "import sys\nfrom matspray.cli import build_parser\nbuild_parser()\n"
        "print(sorted(m for m in ('torch', 'numpy') if m in sys.modules))"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, cwd=PACKAGE_ROOT.parent, timeout=60
    )
    assert loaded.returncode == 0, loaded.stderr
    assert loaded.stdout.strip() == "[]", f"building the CLI parser imports {loaded.stdout.strip()}"


MAX_CLASS_LINES = 250


def test_no_class_is_over_250_lines():
    """A class that long does two jobs (as Pipeline did when it inherited its RunPlan: resolving and running)."""
    long = [
        f"{path.relative_to(PACKAGE_ROOT.parent)}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for path in sorted(PACKAGE_ROOT.rglob("*.py"))
        for node in ast.walk(ast.parse(path.read_text(), str(path)))
        if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > MAX_CLASS_LINES
    ]
    assert not long, "classes over 250 lines (split them):\n" + "\n".join(long)
