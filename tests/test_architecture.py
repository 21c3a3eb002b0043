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

    assert compare_cli.EXIT_FAILED == cli.EXIT_FAILED == 3 and set(cli.EXIT_CODES) == {0, 1, 2, 3, 130, 143}
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


def _is_library(module: str) -> bool:
    """The library: every module but the command-line tools (``pets.tools``, ``pets.experiments``, the forwarding
    modules ``pets.<tool>`` and ``pets.compare``)."""
    from pets.tools import MOVED

    commands = {f"pets.{name}" for name in (*MOVED, "compare")}
    return not module.startswith(("pets.tools", "pets.experiments")) and module not in commands


def test_the_library_is_free_of_the_tools() -> None:
    """No library module imports a tool (``pets.tools``, its shared ``pets.tools.cli`` included; the old paths
    ``pets.<tool>`` only forward to it), and each old path is a forwarding module that resolves to the tool itself."""
    import importlib

    from pets.tools import MOVED

    tools = {f"pets.tools.{name}" for name in MOVED} | {f"pets.{name}" for name in MOVED}
    bad = [
        f"{module} imports {target}"
        for module, imports in _imports().items()
        if _is_library(module)
        for target, names in imports
        if target.startswith("pets.tools") or (target == "pets" and {f"pets.{n}" for n in names} & tools)
    ]
    assert not bad, bad
    old_paths = {f"pets.{name}" for name in MOVED}  # for the command line and old imports, not for the project
    through_old = [
        f"{module} imports {target}"
        for module, imports in _imports().items()
        for target, _ in imports
        if target in old_paths
    ]
    assert not through_old, through_old
    for name in MOVED:
        assert importlib.import_module(f"pets.{name}") is importlib.import_module(f"pets.tools.{name}")
        assert len((ROOT / "pets" / f"{name}.py").read_text().splitlines()) <= 5  # a forwarder, not a copy


def test_the_library_is_free_of_the_experiments() -> None:
    """No library module imports ``pets.experiments`` (the comparison command): what the library needs from it,
    such as the open-loop tool's bootstrap statistics, lives in the library (``pets.stats``)."""
    bad = [
        f"{module} imports {target}"
        for module, imports in _imports().items()
        if _is_library(module)
        for target, names in imports
        if target.startswith("pets.experiments") or (target == "pets" and "experiments" in names)
    ]
    assert not bad, bad


def test_config_error_has_a_module_of_its_own() -> None:
    """``ConfigError`` is defined in ``pets.errors`` and re-exported by ``pets.config`` (every old import works);
    run directories and video take it from ``pets.errors`` without importing the configuration hub."""
    import pets.config
    import pets.errors

    assert pets.config.ConfigError is pets.errors.ConfigError
    assert issubclass(pets.errors.ConfigError, ValueError)
    graph = _imports()
    heavy = [m for m in ("pets.runs.rundir", "pets.runs.video") if any(t == "pets.config" for t, _ in graph[m])]
    assert not heavy, heavy
    assert ("pets.errors", ["ConfigError"]) in graph["pets.config"]


def test_the_library_is_free_of_argparse() -> None:
    """Command lines are parsed only by the tools: no library module imports argparse."""
    bad = []
    for package in ORDER:
        for path in sorted((ROOT / package).rglob("*.py")):
            module = _module_name(path)
            if not _is_library(module):
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
                if isinstance(node, ast.ImportFrom) and node.level == 0:
                    names = [node.module]
                bad += [f"{module} imports {name}" for name in names if name.split(".")[0] == "argparse"]
    assert not bad, bad


#: At most this many modules at the top of ``pets/`` (forwarding modules included); the rest live in
#: subpackages by job (data, planning, learning, runs, tools, experiments).
MAX_TOP_MODULES = 22
MAX_MODULE_LINES = 450
MAX_FUNCTION_LINES = 100
#: Where the size limits apply (the module limit spares the command-line tools in ``pets/tools``).
SIZED = ("pets", "gem_head", "envs", "dynamics")


def _sized_sources(skip: tuple[str, ...]) -> list[Path]:
    return [
        path
        for package in SIZED
        for path in sorted((ROOT / package).rglob("*.py"))
        if not path.relative_to(ROOT).as_posix().startswith(skip)
    ]


def test_few_modules_at_the_top_of_pets() -> None:
    top = sorted(path.name for path in (ROOT / "pets").glob("*.py"))
    assert len(top) <= MAX_TOP_MODULES, f"{len(top)} modules at the top of pets/ (at most {MAX_TOP_MODULES}): {top}"


def test_no_library_module_is_too_long() -> None:
    """No module over MAX_MODULE_LINES lines, the command-line tools' (pets/tools) apart."""
    long = {
        str(path.relative_to(ROOT)): n
        for path in _sized_sources(("pets/tools/",))
        if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert not long, long


def test_no_function_is_too_long() -> None:
    """No function or method over MAX_FUNCTION_LINES lines (its def line to its last), the tools included."""
    long = {
        f"{path.relative_to(ROOT)}:{node.name}": n
        for path in _sized_sources(())
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        if (n := node.end_lineno - node.lineno + 1) > MAX_FUNCTION_LINES
    }
    assert not long, long


def _names_a_kind(node: ast.AST) -> bool:
    """A string constant, or a tuple/list/set of them: a kind name typed in a comparison."""
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return any(_names_a_kind(e) for e in node.elts)
    return isinstance(node, ast.Constant) and isinstance(node.value, str)


def test_group_kinds_dispatch_through_their_tables() -> None:
    """The step error, the rotation error, the per-entry differences and the parts of an observation come from each
    kind's codec (``gem_head.codecs``), its MuJoCo qpos from the kind table (``envs.layout.KIND_QPOS``): no chain of
    comparisons of ``.kind`` with kind names there."""
    where = {
        "pets/learning/evaluation.py": ("_total_squared", "rotation_angles", "entry_differences", "layout_parts"),
        "envs/render.py": ("qpos_from_obs",),
    }
    chains = [
        f"{path}:{node.name}"
        for path, names in where.items()
        for node in ast.walk(ast.parse((ROOT / path).read_text()))
        if isinstance(node, ast.FunctionDef) and node.name in names
        for cmp in ast.walk(node)
        if isinstance(cmp, ast.Compare)
        and any(isinstance(s, ast.Attribute) and s.attr == "kind" for s in (cmp.left, *cmp.comparators))
        and any(_names_a_kind(s) for s in (cmp.left, *cmp.comparators))
    ]
    assert not chains, chains


def test_every_source_file_is_tracked_by_git() -> None:
    """An ignore rule once matched a package folder (``runs/`` matched ``pets/runs/``): a new module there passed
    every test here and was missing from the commit, so a clean checkout could not import the package."""
    import subprocess

    packages = ["pets", "envs", "dynamics", "gem_head", "tests", "docs/scripts", "run_pets.py", "setup.py"]
    listed = subprocess.run(
        ["git", "ls-files", "--others", "--exclude-standard", "--ignored", "--", *packages],
        cwd=ROOT, capture_output=True, text=True, check=True,
    ).stdout.split()  # fmt: skip
    assert [p for p in listed if p.endswith((".py", ".sh", ".toml", ".cfg"))] == []
