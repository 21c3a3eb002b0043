"""The dependency direction of the packages: envs <- dynamics <- gem_head <- pets; no import cycle between
modules; no private name imported across packages. Read from the source with ``ast`` (every import, also the
ones inside functions)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: Each package may import only the packages before it (and itself).
ORDER = ("envs", "dynamics", "gem_head", "pets")


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports() -> dict[str, list[tuple[str, list[str]]]]:
    """module -> [(imported module, imported names)] for every project module."""
    graph = {}
    for package in ORDER:
        for path in sorted((ROOT / package).rglob("*.py")):
            found = []
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    found += [(alias.name, []) for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    found.append((node.module, [alias.name for alias in node.names]))
            graph[_module_name(path)] = [(m, names) for m, names in found if m.split(".")[0] in ORDER]
    return graph


def test_packages_import_only_the_packages_below_them() -> None:
    bad = []
    for module, imports in _imports().items():
        rank = ORDER.index(module.split(".")[0])
        bad += [f"{module} imports {target}" for target, _ in imports if ORDER.index(target.split(".")[0]) > rank]
    assert not bad, bad


def test_no_private_name_crosses_a_package() -> None:
    bad = [
        f"{module} imports {target}.{name}"
        for module, imports in _imports().items()
        for target, names in imports
        for name in names
        if name.startswith("_") and target.split(".")[0] != module.split(".")[0]
    ]
    assert not bad, bad


def test_no_import_cycle_between_modules() -> None:
    graph = _imports()
    modules = set(graph)

    def resolve(target: str, names: list[str]) -> set[str]:
        found = {f"{target}.{n}" for n in names if f"{target}.{n}" in modules}  # from package import module
        return found | ({target} if target in modules else set())

    edges = {m: set().union(*(resolve(t, n) for t, n in imports)) - {m} for m, imports in graph.items()}
    state: dict[str, int] = {}
    cycle: list[str] = []

    def visit(node: str, path: list[str]) -> bool:
        state[node] = 1
        for nxt in sorted(edges[node]):
            if state.get(nxt) == 1:
                cycle.extend(path[path.index(nxt) :] + [node, nxt] if nxt in path else [node, nxt])
                return True
            if nxt not in state and visit(nxt, path + [node]):
                return True
        state[node] = 2
        return False

    assert not any(visit(m, []) for m in sorted(modules) if m not in state), " -> ".join(cycle)


def test_one_exit_code_table() -> None:
    """Every command's exit statuses are pets.tools.cli's: no module defines its own EXIT_* constant."""
    from pets.experiments import cli as compare_cli
    from pets.tools import cli

    assert compare_cli.EXIT_FAILED == cli.EXIT_FAILED == 3 and set(cli.EXIT_CODES) == {0, 2, 3, 130}
    own = [
        str(path.relative_to(ROOT))
        for path in sorted((ROOT / "pets").rglob("*.py"))
        if path.relative_to(ROOT).as_posix() != "pets/tools/cli.py"
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Assign)
        for target in node.targets
        if isinstance(target, ast.Name) and target.id.startswith("EXIT_")
    ]
    assert not own, own


def test_the_library_is_free_of_the_tools() -> None:
    """No module outside ``pets.tools`` imports a tool (the old paths ``pets.<tool>`` only forward to it), and each
    old path is a forwarding module that resolves to the tool itself."""
    import importlib

    from pets.tools import MOVED

    tools = {f"pets.tools.{name}" for name in MOVED} | {f"pets.{name}" for name in MOVED}
    bad = [
        f"{module} imports {target}"
        for module, imports in _imports().items()
        if not module.startswith("pets.tools") and module not in tools
        for target, names in imports
        if target in tools
        or (target == "pets.tools" and set(names) - {"forward"})
        or (target == "pets" and {f"pets.{n}" for n in names} & tools)
    ]
    assert not bad, bad
    for name in MOVED:
        assert importlib.import_module(f"pets.{name}") is importlib.import_module(f"pets.tools.{name}")
        assert len((ROOT / "pets" / f"{name}.py").read_text().splitlines()) <= 5  # a forwarder, not a copy
