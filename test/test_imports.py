"""The package's modules import one another without a circle: every import counted, at the top of a module or
inside a function (an import deferred into a function is how a circle hides)."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "sma_stage"


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path, known: set[str]) -> set[str]:
    """The package's modules a file imports (`from a.b import c` counts a.b.c when that is a module, else a.b)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in known else node.module
                     for alias in node.names]
        else:
            continue
        found.update(name for name in names if name in known)
    return found


def import_graph() -> dict[str, set[str]]:
    paths = {module_name(path): path for path in PACKAGE.rglob("*.py")}
    known = set(paths)
    # a package's __init__ re-exports its modules: an edge into the package is not an edge out of its modules
    return {name: imported_modules(path, known) - {name} for name, path in paths.items()}


def find_circle(graph: dict[str, set[str]]) -> list[str] | None:
    """One circle of the graph (its modules in order, the first repeated at the end), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(name: str) -> list[str] | None:
        state[name] = 1
        stack.append(name)
        for target in sorted(graph.get(name, ())):
            if state.get(target) == 1:
                return stack[stack.index(target):] + [target]
            if target not in state and (circle := visit(target)):
                return circle
        stack.pop()
        state[name] = 2
        return None

    for name in sorted(graph):
        if name not in state and (circle := visit(name)):
            return circle
    return None


def test_the_finder_finds_a_circle_and_passes_a_tree():
    assert find_circle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_circle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_no_module_of_the_package_imports_itself_through_others():
    graph = import_graph()
    assert len(graph) > 50 and "sma_stage.model.identified" in graph
    circle = find_circle(graph)
    assert circle is None, "import circle: " + " -> ".join(circle)


NUMERICAL_CORE = ("sma_stage.model", "sma_stage.identify", "sma_stage.plant", "sma_stage.control", "sma_stage.io")
ROS_PACKAGES = ("rclpy", "rcl_interfaces", "std_msgs", "sensor_msgs", "diagnostic_msgs", "std_srvs", "rosgraph_msgs",
                "builtin_interfaces", "launch", "launch_ros")


def foreign_imports(path: Path) -> set[str]:
    """The top-level names of every module a file imports from outside the package, anywhere in it."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module.split(".")[0])
    return found - {"sma_stage"}


def test_the_numerical_core_imports_no_ros_package_even_through_the_package():
    """model/, identify/, plant/, control/ and io/ run without ROS: no ROS import in them, nor in any module of the
    package they import (rosbags, pure Python, reads bags without ROS)."""
    graph = import_graph()
    paths = {module_name(path): path for path in PACKAGE.rglob("*.py")}
    core = [name for name in graph if name.startswith(NUMERICAL_CORE)]
    assert len(core) > 40
    reached, todo = set(), list(core)
    while todo:
        name = todo.pop()
        if name not in reached:
            reached.add(name)
            todo.extend(graph[name])
    with_ros = {name: sorted(foreign_imports(paths[name]) & set(ROS_PACKAGES)) for name in reached}
    assert not any(with_ros.values()), {name: found for name, found in with_ros.items() if found}
    assert foreign_imports(paths["sma_stage.nodes.stage_node"]) & set(ROS_PACKAGES), "the check sees ROS imports"
