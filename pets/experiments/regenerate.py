"""``pets.compare report``: make every published file (:data:`pets.experiments.published.PRODUCTS`) and every
generated block of the docs from the committed per-seed rows, then write them (``report``) or compare them with
what is committed (``report --check``: the first differing file and line).

A generated block in one of :data:`BLOCK_FILES` is delimited by ``<!-- report:NAME -->`` and
``<!-- /report:NAME -->`` (each on a line of its own); its content is :data:`BLOCKS`' ``NAME`` rendered from the
generated files. Text outside the blocks is never touched.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import re
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from pets.experiments import published
from pets.experiments.answer import answer_table, coverage_table, later_offline_table, runs_coverage_table
from pets.experiments.arguments import PROG
from pets.experiments.gate_published import (
    ablation_table,
    compute_table,
    cost_table,
    episode_ends_table,
    fall_prediction_table,
    frozen_planning_table,
    gate_table,
    oracle_table,
    peer_table,
    pilots_table,
    reward_prediction_table,
)
from pets.experiments.offline_tables import (
    GEMSE_METRICS,
    curves_table,
    data_sets_table,
    own_comparison_table,
    paper_table,
    versus_table,
)
from pets.experiments.studies import composition
from pets.experiments.studies.locomotion import runs_table, summary_table
from pets.experiments.studies.online import study_table
from pets.experiments.studies.planning import planning_table
from pets.runs.fileio import atomic_write_bytes
from pets.tools.cli import EXIT_DIFFERS, fail

#: The docs that may hold generated blocks.
BLOCK_FILES = (
    *("README.md", "docs/results.md", "docs/experiments.md", "docs/planning.md"),
    *("docs/studies/locomotion_gate.md", "docs/studies/online_locomotion.md", "docs/studies/composition.md"),
)
#: Block name -> its content, rendered from a tree (the repository or its generated copy).
BLOCKS: dict[str, Callable[[Path], str]] = {
    "answer": answer_table,
    "later-offline": later_offline_table,
    **{f"offline-paper-{s}": functools.partial(paper_table, study=s) for s in published.ORIGINAL},
    "offline-paper-own": own_comparison_table,
    "offline-gemse-versus": functools.partial(versus_table, study="gemse"),
    **{
        f"offline-gemse-{e}": functools.partial(paper_table, study="gemse", env=e, metrics=GEMSE_METRICS)
        for e in ("halfcheetah", "hopper", "walker2d", "ant", "humanoid")
    },
    "offline-data-sets": data_sets_table,
    "offline-learning-curves": curves_table,
    "planning": planning_table,
    **{f"online-{s}": functools.partial(study_table, study=s) for s in published.ONLINE if "time_to_solve" not in s},
    "online-replan5": functools.partial(study_table, study=("online_idp_replan5", "online_reacher_replan5")),
    "coverage": coverage_table,
    "runs-coverage": runs_coverage_table,
    "locomotion-oracle": oracle_table,
    "locomotion-pilots": pilots_table,
    "locomotion-episode-ends": episode_ends_table,
    "locomotion-frozen-planning": frozen_planning_table,
    "locomotion-fall-prediction": fall_prediction_table,
    "locomotion-reward-prediction": reward_prediction_table,
    "locomotion-gate": gate_table,
    "locomotion-ablation": ablation_table,
    "locomotion-peer": peer_table,
    "locomotion-compute": compute_table,
    "locomotion-cost": cost_table,
    "online-locomotion-runs": runs_table,
    "online-locomotion": summary_table,
    "composition": composition.study_table,
}
_BLOCK = re.compile(r"(<!-- report:(?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /report:(?P=name) -->)", re.DOTALL)


class ReportError(ValueError):
    """A generated block that cannot be rendered (an unknown name, an unclosed marker)."""


@contextlib.contextmanager
def generated_tree(root: Path) -> Iterator[Path]:
    """A temporary copy of ``root``'s docs/results in which every product has been made (products read their
    inputs there, so a generated summary feeds the headline as it would once written)."""
    with tempfile.TemporaryDirectory(prefix="pets-report-") as tmp:
        tree = Path(tmp)
        shutil.copytree(root / published.RESULTS, tree / published.RESULTS)
        (tree / "docs" / "figures").mkdir(parents=True)
        with contextlib.chdir(tree):
            for product in published.PRODUCTS:
                product.make()
        yield tree


def render_blocks(text: str, tree: Path) -> str:
    """``text`` with the content of every generated block rendered from ``tree``; ReportError for a marker
    without its end or an unknown block name."""
    opened = re.findall(r"<!-- report:([\w-]+) -->", text)
    closed = re.findall(r"<!-- /report:([\w-]+) -->", text)
    if sorted(opened) != sorted(closed):
        raise ReportError(f"unmatched report markers: opened {opened}, closed {closed}")

    def render(match: re.Match[str]) -> str:
        name = match["name"]
        if name not in BLOCKS:
            raise ReportError(f"unknown generated block {name!r}; known: {', '.join(BLOCKS)}")
        return f"{match[1]}{BLOCKS[name](tree).rstrip()}\n{match[4]}"

    return _BLOCK.sub(render, text)


def _first_difference(committed: bytes, generated: bytes) -> str:
    """``line N: committed '...', generated '...'`` of the first line that differs."""
    old, new = committed.decode(errors="replace").split("\n"), generated.decode(errors="replace").split("\n")
    for i, (a, b) in enumerate(zip(old, new), start=1):
        if a != b:
            return f"line {i}: committed {a[:80]!r}, generated {b[:80]!r}"
    n = min(len(old), len(new)) + 1
    return f"line {n}: the {'committed' if len(old) < len(new) else 'generated'} file ends there"


def _generated(root: Path, tree: Path) -> Iterator[tuple[str, bytes | None, bytes]]:
    """``(path, committed bytes or None, generated bytes)`` of every product output and every block file."""
    for path in published.outputs():
        target = root / path
        yield path, target.read_bytes() if target.is_file() else None, (tree / path).read_bytes()
    for path in BLOCK_FILES:
        target = root / path
        if target.is_file():
            text = target.read_text()
            yield path, text.encode(), render_blocks(text, tree).encode()


def check(root: Path) -> list[str]:
    """One line per generated file that differs from what is committed under ``root`` and per generated block that
    no block file holds any more (empty: none)."""
    with generated_tree(root) as tree:
        return [
            f"{path}: not committed" if old is None else f"{path}: {_first_difference(old, new)}"
            for path, old, new in _generated(root, tree)
            if old != new
        ] + _removed_blocks(root)


def _removed_blocks(root: Path) -> list[str]:
    """One line per name of :data:`BLOCKS` whose markers are in none of the :data:`BLOCK_FILES` under ``root`` (the
    block deleted with its markers, or its file gone): a block never rendered was never checked either."""
    found = set()
    for path in (root / name for name in BLOCK_FILES):
        found |= set(re.findall(r"<!-- report:([\w-]+) -->", path.read_text())) if path.is_file() else set()
    return [
        f"<!-- report:{name} -->: in none of {', '.join(BLOCK_FILES)}; restore the block with its markers"
        for name in BLOCKS
        if name not in found
    ]


def write(root: Path) -> list[str]:
    """Write every generated file and block under ``root``; returns the paths whose bytes changed."""
    changed = []
    with generated_tree(root) as tree:
        for path, old, new in list(_generated(root, tree)):
            if old != new:
                atomic_write_bytes(root / path, new)
                changed.append(path)
    return changed


def report_main(args: argparse.Namespace) -> int:
    """Write (or with ``--check`` compare) every generated file; 0, or 1 when ``--check`` finds a difference (the
    first one named on stderr, in one line); exit 2 with one line for a root that is not the repository."""
    root = args.root
    if not (root / published.RESULTS).is_dir():
        fail(f"{PROG} report", f"{root}: no {published.RESULTS} here; run from the repository root or give --root")
    try:
        if args.check:
            differ = check(root)
            if differ:
                print(
                    f"{PROG} report --check: {differ[0]} ({len(differ)} file(s) differ from what report generates; "
                    f"run {PROG} report to regenerate)",
                    file=sys.stderr,
                )
                return EXIT_DIFFERS
            print(f"{PROG} report --check: {len(published.outputs())} files and the generated blocks are up to date")
            return 0
        changed = write(root)
    except ValueError as err:  # a ReportError, or a committed input a product cannot read (said in one line)
        fail(f"{PROG} report", str(err))
    except FileNotFoundError as err:  # a root without the committed rows a product is made from
        fail(f"{PROG} report", f"{err.filename} is missing: report makes its files from a checkout's committed rows")
    print(f"{PROG} report: {len(changed)} file(s) written{': ' + ', '.join(changed) if changed else ''}")
    return 0
