"""No import cycles: between the files of mapex/, services/ and deploy/, nor between packages.

Every .py file is parsed with `ast` (nothing is imported). Each `import`, at module level or
inside a function, is an edge from its file's module to the project module it names:
relative imports are resolved, `from a.b import c` is module a.b.c when that is a module,
else a.b. A package is the folder of a module (mapex.prediction, services.bridges, ...; the
modules directly in mapex/, services/ and deploy/ are each their own, see `package_of`); the
package graph has an edge A -> B when a module of A imports a module of B, A != B.
"""

from __future__ import annotations

import ast
import subprocess
from collections.abc import Iterable, Mapping
from pathlib import Path

import pytest
from commands_at_once import helps_at_once

ROOT = Path(__file__).resolve().parents[1]
TOP_PACKAGES = ("mapex", "services", "deploy")

Graph = Mapping[str, set[str]]

# moved modules with a command line: old `python -m` name (a shim now) -> the module
MOVED_COMMANDS = {
    "mapex.prediction.train": "mapex.training.train",
    "mapex.prediction.evaluate": "mapex.training.evaluate",
    "services.watch": "services.bridges.watch",
    "services.web": "services.bridges.web",
    "services.ros2": "services.bridges.ros2",
    "services.record": "services.bridges.record",
}


def module_files(root: Path = ROOT) -> dict[str, Path]:
    """Module name -> file, for every .py file under the top-level packages."""
    modules = {}
    for top in TOP_PACKAGES:
        for path in sorted((root / top).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join(parts)] = path
    return modules


def imported_names(module: str, path: Path, is_package: bool) -> Iterable[str]:
    """The dotted names `module`'s file imports, relative imports resolved; `from a.b import
    c` is a.b.c, and the caller falls back to a.b when that is no module."""
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                package = module.split(".") if is_package else module.split(".")[:-1]
                anchor = package[: len(package) - (node.level - 1)]
                base = ".".join([*anchor, *([base] if base else [])])
            for alias in node.names:
                yield base if alias.name == "*" else f"{base}.{alias.name}"


def module_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module -> the project modules it imports (function-level imports included)."""
    files = module_files(root)
    graph: dict[str, set[str]] = {module: set() for module in files}
    for module, path in files.items():
        for name in imported_names(module, path, path.name == "__init__.py"):
            target = _project_module(name, files)
            if target is not None and target != module:
                graph[module].add(target)
    return graph


def _project_module(name: str, files: Mapping[str, Path]) -> str | None:
    """The longest prefix of `name` that is a project module (a.b.c, else a.b, ...), or None."""
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        if (candidate := ".".join(parts[:end])) in files:
            return candidate
    return None


def package_of(module: str, files: Mapping[str, Path]) -> str:
    """The folder a module's file lies in, as a dotted name (a package's __init__ lies in its
    own folder), except for the modules directly in mapex/, services/ and deploy/: each of
    those is a node of its own. Those folders hold both the base layer (mapex.grid,
    services.codec) and the entry points (mapex.cli, services.up), so as one node they
    would be in a cycle with every subpackage; what stays forbidden is a loop that leaves a
    subpackage and comes back to it (mapex.prediction -> mapex.explorer -> mapex.methods ->
    mapex.prediction)."""
    folder = module if files[module].name == "__init__.py" else module.rpartition(".")[0]
    return module if folder in TOP_PACKAGES else folder


def package_graph(modules: Graph, root: Path = ROOT) -> dict[str, set[str]]:
    """Package -> the other packages its modules import."""
    files = module_files(root)
    graph: dict[str, set[str]] = {package_of(m, files): set() for m in modules}
    for module, targets in modules.items():
        source = package_of(module, files)
        for target in targets:
            if (package := package_of(target, files)) != source:
                graph[source].add(package)
    return graph


def cycles(graph: Graph) -> list[list[str]]:
    """One cycle (first node repeated at the end) per strongly connected component of more
    than one node, found with Tarjan's algorithm."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(node: str) -> None:  # recursion depth is bounded by the number of modules
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return [_cycle_through(component, graph) for component in sorted(components)]


def _cycle_through(component: list[str], graph: Graph) -> list[str]:
    """A shortest cycle from the component's first node back to it, inside the component."""
    start, members = component[0], set(component)
    came_from: dict[str, str] = {}
    frontier = [start]
    while frontier:
        next_frontier = []
        for node in frontier:
            for target in sorted(graph[node] & members):
                if target == start:
                    path = [node]
                    while path[-1] != start:
                        path.append(came_from[path[-1]])
                    return [*reversed(path), start]
                if target not in came_from:
                    came_from[target] = node
                    next_frontier.append(target)
        frontier = next_frontier
    raise AssertionError(f"{component} is no strongly connected component")


def describe(found: list[list[str]]) -> str:
    return "\n".join(" -> ".join(cycle) for cycle in found)


def test_the_graph_sees_relative_function_level_and_from_imports(tmp_path: Path) -> None:
    files = {
        "mapex/__init__.py": "",
        "mapex/grid.py": "",
        "mapex/cli.py": "def main():\n    from mapex.methods import base\n",
        "mapex/methods/__init__.py": "from .base import Method\n",
        "mapex/methods/base.py": "from .. import grid\nimport mapex.prediction.net as net\n",
        "mapex/prediction/__init__.py": "from mapex.prediction import net\n",
        "mapex/prediction/net.py": "import numpy\nfrom mapex.grid import FREE\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    graph = module_graph(tmp_path)
    assert graph == {
        "mapex": set(),
        "mapex.grid": set(),
        "mapex.cli": {"mapex.methods.base"},
        "mapex.methods": {"mapex.methods.base"},
        "mapex.methods.base": {"mapex.grid", "mapex.prediction.net"},
        "mapex.prediction": {"mapex.prediction.net"},
        "mapex.prediction.net": {"mapex.grid"},
    }
    assert package_graph(graph, tmp_path) == {
        "mapex": set(),
        "mapex.grid": set(),
        "mapex.cli": {"mapex.methods"},
        "mapex.methods": {"mapex.grid", "mapex.prediction"},
        "mapex.prediction": {"mapex.grid"},
    }


def test_cycles_finds_a_loop_and_reports_it_in_order() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"e"}}
    assert cycles(graph) == [["a", "b", "c", "a"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_prediction_does_not_reach_the_explorer_or_the_methods() -> None:
    """The predictors sit below the methods that use them; the offline training code, which
    explores worlds with the methods, is mapex.training."""
    graph = module_graph()
    reached: set[str] = set()
    todo = [m for m in graph if in_package(m, "mapex.prediction")]
    while todo:
        if (module := todo.pop()) not in reached:
            reached.add(module)
            todo.extend(graph[module])
    above = ("mapex.explorer", "mapex.episode", "mapex.methods", "mapex.team", "mapex.training")
    assert not sorted(m for m in reached if any(in_package(m, name) for name in above))


def in_package(module: str, name: str) -> bool:
    return module == name or module.startswith(name + ".")


def test_no_import_cycle_between_files() -> None:
    found = cycles(module_graph())
    assert not found, f"import cycles between modules:\n{describe(found)}"


def test_no_import_cycle_between_packages() -> None:
    found = cycles(package_graph(module_graph()))
    assert not found, f"import cycles between packages:\n{describe(found)}"


@pytest.fixture(scope="module")
def moved_helps() -> dict[str, subprocess.CompletedProcess]:
    """`python -m MODULE --help` of every moved command by its old and its new name, all run
    at once (each is mostly imports), but those tests/test_docs.py ran in this session."""
    modules = sorted({*MOVED_COMMANDS, *MOVED_COMMANDS.values()})
    return dict(zip(modules, helps_at_once([(m,) for m in modules]), strict=True))


@pytest.mark.parametrize("old, new", sorted(MOVED_COMMANDS.items()))
def test_a_moved_command_still_runs_by_its_old_name(old: str, new: str, moved_helps) -> None:
    by_old_name, by_new_name = moved_helps[old], moved_helps[new]
    assert by_old_name.returncode == 0, by_old_name.stderr
    assert by_old_name.stdout == by_new_name.stdout
    assert len((ROOT / Path(*old.split("."))).with_suffix(".py").read_text().splitlines()) < 10
