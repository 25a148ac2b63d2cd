"""The package's import graph (read from the sources, lazy imports inside functions included) runs
one way, as docs/architecture.md draws it: no module imports, directly or through others, a
module that imports it back; the ground floor (fields, linalg, compiled, errors, lazy) imports
nothing above it; the solid, the fluids and the coupling do not import each other or anything
above them; io and render read files and do not import the solvers."""

import ast
from pathlib import Path

import fishsim

PACKAGE = Path(fishsim.__file__).resolve().parent
GROUND = ("fishsim.fields", "fishsim.linalg", "fishsim.compiled", "fishsim.errors", "fishsim.lazy")
SOLVERS = ("fishsim.solid", "fishsim.fluid", "fishsim.coupling")
ABOVE_SOLVERS = ("fishsim.rollout", "fishsim.episode", "fishsim.config", "fishsim.commands", "fishsim.learn",
                 "fishsim.optimize", "fishsim.swim_study", "fishsim.solid_study", "fishsim.cli", "fishsim.render",
                 "fishsim.io", "fishsim.multirun")


def _modules() -> dict[str, Path]:
    modules = {}
    for path in PACKAGE.rglob("*.py"):
        parts = ("fishsim", *path.relative_to(PACKAGE).with_suffix("").parts)
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def _graph() -> dict[str, set[str]]:
    """module -> the fishsim modules it imports (``from a.b import c`` names a.b.c if that is a
    module, else a.b; importing the root package for its version counts as nothing)."""
    modules = _modules()

    def module_of(name: str) -> str:
        while name not in modules:
            name = name.rpartition(".")[0]
        return name

    graph = {}
    for name, path in modules.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_bytes())):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("fishsim"):
                targets |= {module_of(f"{node.module}.{alias.name}") for alias in node.names}
            elif isinstance(node, ast.Import):
                targets |= {module_of(a.name) for a in node.names if a.name.startswith("fishsim")}
        graph[name] = targets - {name, "fishsim"}
    return graph


def _within(name: str, packages: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in packages)


def test_no_module_imports_one_that_imports_it_back():
    graph, state, cycles = _graph(), {}, []

    def visit(name: str, path: list[str]) -> None:
        state[name] = "open"
        for target in sorted(graph[name]):
            if state.get(target) == "open":
                cycles.append(path[path.index(target):] + [target])
            elif target not in state:
                visit(target, path + [target])
        state[name] = "done"

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    assert not cycles, cycles


def test_packages_import_only_downwards():
    graph = _graph()
    for name, targets in graph.items():
        if _within(name, GROUND):
            assert all(_within(t, GROUND) for t in targets), (name, targets)
        for solver in SOLVERS:
            if _within(name, (solver,)):
                others = tuple(s for s in SOLVERS if s != solver) + ABOVE_SOLVERS
                assert not [t for t in targets if _within(t, others)], (name, targets)
        if _within(name, ("fishsim.io", "fishsim.render")):
            solvers = [t for t in targets if _within(t, SOLVERS + ("fishsim.rollout", "fishsim.episode"))]
            assert solvers in ([], ["fishsim.solid.muscles"]), (name, solvers)   # the preview's muscle geometry
