"""The import graph runs one way: every package imports only from its own floor or a lower one, and no two
modules import each other, directly or round a circle (function-level imports included)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: The floors, lowest first (CONTRIBUTING.md, "Layout"): a unit is a subpackage or a top-level module of
#: spoil_torchrl (``recipes`` for the recipes); each may import from its own floor and the floors below.
FLOORS = [
    {
        "(top)",
        "console",
        "devices",
        "divergence",
        "errors",
        "files",
        "precision",
        "rules",
        "stack",
        "stopping",
        "tasks",
    },
    {"envs"},
    {"modules"},
    {"objectives"},
    {"zoo"},
    {"data"},
    {"eval"},
    {"trainers"},
    {"algorithms", "tabular"},
    {"runs"},
    {"experts", "reporting"},
    {"inspect"},
    {"recipes"},
]
FLOOR = {unit: level for level, units in enumerate(FLOORS) for unit in units}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[0] == "recipes":
        parts = ["spoil_torchrl", *parts]
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "(top)"


def _runtime_nodes(tree: ast.AST):
    """Every node of ``tree`` except those under ``if TYPE_CHECKING:`` (annotations only, never imported)."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            continue
        yield node
        yield from _runtime_nodes(node)


def _imports() -> dict[str, set[str]]:
    """Each module of the package and the recipes -> the spoil_torchrl modules it imports, anywhere in it."""
    graph: dict[str, set[str]] = {}
    files = [*(ROOT / "spoil_torchrl").rglob("*.py"), *(ROOT / "recipes").glob("*.py")]
    modules = {_module_name(path) for path in files}
    for path in files:
        name, targets = _module_name(path), set()
        for node in _runtime_nodes(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("spoil_torchrl"):
                targets.add(node.module)
                # ``from spoil_torchrl.x import y`` imports the module x.y when y is one
                targets |= {f"{node.module}.{a.name}" for a in node.names} & modules
            elif isinstance(node, ast.Import):
                targets |= {a.name for a in node.names if a.name.startswith("spoil_torchrl")}
        graph[name] = {t for t in targets if t != name}
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One circle of ``graph``, or ``None``."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for target in sorted(graph.get(node, ())):
            if state.get(target) == 1:
                return stack[stack.index(target) :] + [target]
            if target not in state and (found := visit(target)) is not None:
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)) is not None:
            return found
    return None


def test_every_unit_has_a_floor():
    units = {_unit(module) for module in _imports()}
    assert units <= set(FLOOR), f"give these a floor in FLOORS: {sorted(units - set(FLOOR))}"


def test_no_import_runs_to_a_higher_floor():
    upward = sorted(
        f"{module} -> {target}"
        for module, targets in _imports().items()
        for target in targets
        if FLOOR[_unit(target)] > FLOOR[_unit(module)]
    )
    assert upward == []


def test_no_package_imports_another_round_a_circle():
    units: dict[str, set[str]] = {}
    for module, targets in _imports().items():
        units.setdefault(_unit(module), set()).update(_unit(t) for t in targets if _unit(t) != _unit(module))
    assert _cycle(units) is None


def test_no_module_imports_another_round_a_circle():
    graph = _imports()
    # a package imports its own modules (its __init__ re-exports them); that is not a circle of two concepts
    graph = {
        m: {t for t in ts if not m.startswith(t + ".") or t == "spoil_torchrl"} for m, ts in graph.items()
    }
    assert _cycle(graph) is None


def test_the_checker_finds_a_circle_and_an_upward_import():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None
    assert FLOOR[_unit("spoil_torchrl.runs.lifecycle")] > FLOOR[_unit("spoil_torchrl.data.buffers")]
