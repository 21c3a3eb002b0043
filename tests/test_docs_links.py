"""What README.md and docs/ point at exists: every relative link, every repository path they name (``docs/...``,
``pets/...``, ``tests/...``, a figure), and docs/layout.md names every module of the packages and every page of
docs/. Reading files only. Left out: the dated history (docs/results_history.md: paths as they were then).

A named path may be a pattern: ``{a,b}`` alternatives, an upper-case or shell placeholder (``paper_ENV_runs.csv``,
``paper_${e}_summary.csv``, ``pets/X.py``, ``_sS.csv``: any name there; the repository's files are named in lower
case) or an output stem (``--out docs/results/locomotion_gate``: the files it starts)."""

from __future__ import annotations

import glob
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").rglob("*.md") if p.name != "results_history.md")]
PACKAGES = ("pets", "envs", "dynamics", "gem_head")
LINK = re.compile(r"\]\(([^)\s]+)\)")
PATH = re.compile(
    r"(?<![\w/.-])((?:docs|pets|tests|envs|dynamics|gem_head|\.ci)/[\w./*{},-]*[\w*/}]|run_pets\.py|pyproject\.toml)"
)
#: Upper case in a path is a placeholder: the repository's files are named in lower case.
PLACEHOLDER = re.compile(r"[A-Z][A-Z0-9]*")


def _expand(path: str) -> list[str]:
    """``path`` with each ``{a,b}`` expanded."""
    m = re.search(r"\{([^{}]*)\}", path)
    if m is None:
        return [path]
    return [q for alt in m.group(1).split(",") for q in _expand(path[: m.start()] + alt.strip() + path[m.end() :])]


def _exists(path: str) -> bool:
    pattern = PLACEHOLDER.sub("*", path)
    if "*" in pattern:
        return any(ROOT.glob(pattern))
    stem = ROOT / path
    return stem.exists() or any(stem.parent.glob(glob.escape(stem.name) + "[_.]*"))  # a file, a folder or a stem


def _mentions() -> list[tuple[str, str, str]]:
    """``(where, kind, text)`` of every relative link and named repository path of the docs."""
    found = []
    for doc in DOCS:
        for number, line in enumerate(doc.read_text().splitlines(), 1):
            where = f"{doc.relative_to(ROOT).as_posix()}:{number}"
            for m in LINK.finditer(line):
                target = m.group(1).partition("#")[0]
                if target and not re.match(r"[a-z]+:", target):
                    found.append((where, "link", (doc.parent / target).resolve().relative_to(ROOT).as_posix()))
            shell = re.sub(r"\$\{?\w+\}?", "VAR", line)  # docs/results/paper_${e}_summary.csv: a placeholder
            named = [m.group(1).rstrip(".") for m in PATH.finditer(shell)]
            # {a,b} wrapped onto the next line: not checked
            found += [(where, "path", p) for n in named if n.count("{") == n.count("}") for p in _expand(n)]
    return found


MENTIONS = _mentions()


def test_the_docs_name_paths_to_check():
    assert len(MENTIONS) > 300 and {kind for _, kind, _ in MENTIONS} == {"link", "path"}


def test_every_link_and_named_path_exists():
    missing = [f"{where}: {kind} {text}" for where, kind, text in MENTIONS if not _exists(text)]
    assert not missing, "\n".join(missing)


def test_layout_names_every_module():
    """Each module of the packages by its path, or by its name in a row that names a path of its folder (the
    forwarding ``pets/X.py`` of a tool by that row's ``python -m pets.X``)."""
    rows = [line for line in (ROOT / "docs" / "layout.md").read_text().splitlines() if line.startswith("| `")]
    missing = []
    for module in sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py")):
        path = module.relative_to(ROOT).as_posix()
        folder = module.parent.relative_to(ROOT).as_posix() + "/"
        if module.name == "__init__.py" and module.parent.name != "planners":
            continue
        if "forward(__name__" in module.read_text():
            continue
        if not any(
            f"`{path}`" in row
            or (
                re.search(rf"`{re.escape(folder)}[\w.]*`", row.split(" | ")[0])
                and re.search(rf"`{re.escape(module.stem)}(\.py)?`", row)
            )
            for row in rows
        ):
            missing.append(path)
    assert not missing, f"docs/layout.md does not name: {missing}"


@pytest.mark.parametrize("page", sorted(p.name for p in (ROOT / "docs").glob("*.md")))
def test_layout_names_every_page(page):
    assert f"`{page}`" in (ROOT / "docs" / "layout.md").read_text()
