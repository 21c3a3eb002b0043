"""Report files: CSV tables written atomically and the number formats of the markdown tables."""

from __future__ import annotations

import csv
import io
import math
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from pets.runs.fileio import atomic_write_bytes

#: Seed of every bootstrap in the summaries and plots (the same numbers on every rerun).
BOOT_SEED = 0


def write_csv(path: Path, rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> None:
    """Write ``rows`` (floats at full precision) atomically."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(path, buf.getvalue().encode())


def fmt(x: float, digits: int = 4) -> str:
    """A number for a markdown table: ``digits`` significant digits, whole numbers from 10^digits up to 10^9
    written out (``13333``, not ``1.333e+04``), ``nan``/``inf`` spelt out."""
    if x is None or not math.isfinite(x):
        return str(x)
    if 10**digits <= abs(x) < 1e9:
        return f"{x:.0f}"
    return f"{x:.{digits}g}"


def fmt_ci(s: Mapping[str, float]) -> str:
    """``mean [ci_low, ci_high]`` of a :func:`pets.stats.bootstrap.summarise` result."""
    return f"{fmt(s['mean'])} [{fmt(s['ci_low'])}, {fmt(s['ci_high'])}]"


def fmt_interval(
    value: float | None, low: float | None, high: float | None, missing: str = "n/a", digits: int = 4
) -> str:
    """``value [low, high]`` (``digits`` significant digits), or ``missing`` when any of the three is absent or not
    finite (never a bare nan/inf)."""
    if any(v is None or not math.isfinite(v) for v in (value, low, high)):
        return missing
    return f"{fmt(value, digits)} [{fmt(low, digits)}, {fmt(high, digits)}]"


def csv_number(text: str | None) -> float:
    """A number read from a CSV cell: NaN for an empty cell (how the summaries write a missing value)."""
    return float(text) if text not in (None, "") else math.nan


def disagreement_lines(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Markdown lines naming the rows (env / model [/ planner] [/ metric at h]) whose bootstrap CI and exact test
    disagree, from their ``ci_exact_note`` (:func:`pets.experiments.statistics.ci_exact_note`); no lines when none
    do."""
    notes = [
        " / ".join(str(r[k]) for k in ("env", "model", "planner", "metric") if r.get(k))
        + (f" at h={r['horizon']}" if r.get("horizon") else "")
        + f": {r['ci_exact_note']}"
        for r in rows
        if r.get("ci_exact_note")
    ]
    if not notes:
        return []
    text = "Where the bootstrap CI and the exact test disagree (the exact p carries a claim): "
    return [text + "; ".join(notes) + ".", ""]


def md_table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    """A markdown table of ``rows`` (cells already formatted) under ``header``."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def read_csv_rows(path: Path, error: type[Exception] = ValueError) -> list[dict[str, str]]:
    """The rows of a CSV file; ``error`` (one line naming the file) for a file that is not text (a binary file)."""
    try:
        with Path(path).open(newline="") as f:
            return list(csv.DictReader(f))
    except (UnicodeDecodeError, csv.Error) as err:
        raise error(f"{path}: not a text CSV file ({type(err).__name__}: {str(err)[:80]})") from None


def merge_committed(
    path: Path, rows: Sequence[Mapping[str, str]], key: Sequence[str], progress: str | None = None
) -> tuple[list[dict[str, str]], int]:
    """``rows`` (cells as text) merged into the CSV already at ``path``: the committed rows in their order, those of
    a ``key`` that ``rows`` has replaced by all of ``rows``' rows of that key (several for a curve), then the keys
    that are new. A committed row whose run directory is no longer on this machine (a finished run, a replaced
    machine) is kept as it is, never lost by rewriting the table (a line on stderr says how many). With
    ``progress`` (a column such as ``env_steps``), a key's committed rows that got further than its new rows (a run
    lost with its machine and started again under its name) are kept too, until the new rows pass them (a line
    names them). Returns the rows and how many were kept."""
    new: dict[tuple[str, ...], list[dict[str, str]]] = {}
    for r in rows:
        new.setdefault(tuple(r[k] for k in key), []).append(dict(r))
    if not path.is_file():
        return [r for group in new.values() for r in group], 0
    committed = read_csv_rows(path)
    if progress is not None:
        behind = _behind_committed(committed, new, key, progress)
        if behind:
            names = ", ".join("/".join(k) for k in sorted(behind))
            print(f"{path}: kept the committed rows of {names} (further in {progress} than the new)", file=sys.stderr)
            new = {k: group for k, group in new.items() if k not in behind}
    out: list[dict[str, str]] = []
    placed: set[tuple[str, ...]] = set()
    kept = 0
    for r in committed:
        k = tuple(r.get(c, "") for c in key)
        if k not in new:
            out.append(r)
            kept += 1
        elif k not in placed:
            out += new[k]
            placed.add(k)
    if kept:
        print(f"{path}: kept {kept} committed rows of runs (or files) not given", file=sys.stderr)
    return out + [r for k, group in new.items() if k not in placed for r in group], kept


def _behind_committed(
    committed: Sequence[Mapping[str, str]],
    new: Mapping[tuple[str, ...], Sequence[Mapping[str, str]]],
    key: Sequence[str],
    progress: str,
) -> set[tuple[str, ...]]:
    """The keys whose new rows reach less far in ``progress`` (the largest value of the column) than the committed
    rows of the key."""

    def reach(group: Sequence[Mapping[str, str]]) -> float:
        return max((float(r[progress]) for r in group if r.get(progress, "") != ""), default=0.0)

    before: dict[tuple[str, ...], list[Mapping[str, str]]] = {}
    for r in committed:
        before.setdefault(tuple(r.get(c, "") for c in key), []).append(r)
    return {k for k, group in new.items() if k in before and reach(group) < reach(before[k])}


def write_rounded_csv(
    path: Path, rows: Sequence[Mapping[str, Any]], columns: Sequence[str], keep: Sequence[str] = ()
) -> list[dict[str, str]]:
    """The rows with their cells as :func:`cell_text` shows them, written by :func:`write_csv`. ``keep``
    (key columns): merged into the committed file, its rows of other keys kept, and a key's committed rows kept
    while its new rows have fewer env steps (:func:`merge_committed`; a line says which). Returns the rows
    written."""
    text = [{c: cell_text(r[c]) for c in columns} for r in rows]
    progress = "env_steps" if "env_steps" in columns else None
    text = merge_committed(path, text, keep, progress)[0] if keep else text
    write_csv(path, text, columns)
    return text


def cell_text(v: Any) -> str:
    """A cell as the rounded CSVs write it: 6 significant digits, NaN and None empty."""
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.6g}"
    return str(v)


def machine_label(host: str | None, cpu: str | None) -> str:
    """A machine as the summaries name it: ``host (CPU)``, ``?`` / ``CPU not recorded`` where unknown."""
    return f"{host or '?'} ({cpu or 'CPU not recorded'})"


def provenance_lines(
    seeds: str, command: str | None, settings: str, machines: Iterable[Iterable[str]], source: str
) -> list[str]:
    """Markdown of what a reader needs to redo a comparison: its ``seeds`` (as listed), the command that wrote the
    summary (when given), where each run's ``settings`` are and the machines the runs ran on (``machines``: each
    run's :func:`machine_label` s, a run on several counting on each; ``source``: the files that record them)."""
    count: dict[str, int] = {}
    for labels in machines:
        for label in set(labels):
            count[label] = count.get(label, 0) + 1
    ran_on = "; ".join(f"{m}: {n} run{'s' if n > 1 else ''}" for m, n in sorted(count.items()))
    return [
        "## How the runs were made",
        "",
        f"- seeds: {seeds}",
        *([f"- command: `{command}`"] if command else []),
        f"- settings: {settings}",
        f"- machines ({source}): {ran_on or 'not recorded'}",
        "",
    ]
