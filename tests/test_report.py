"""``pets.compare report``: the published summaries and the docs' generated blocks are what the generators make
from the committed per-seed rows (``--check`` on the committed tree), a drifted file is named with its first
differing line, blocks are rewritten between their markers only, and every committed file under docs/results is
generated, per-seed data, or excluded with a reason."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pets.experiments import published, regenerate
from pets.experiments.cli import main
from pets.tools.cli import EXIT_DIFFERS

ROOT = Path(__file__).resolve().parents[1]


def test_report_check_passes_on_the_committed_tree() -> None:
    """The CI gate: every generated file and block equals what is committed, byte for byte."""
    proc = subprocess.run(
        [sys.executable, "-m", "pets.compare", "report", "--check"],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr
    assert "up to date" in proc.stdout


def _small_tree(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, names: set[str]) -> Path:
    """A root holding a copy of docs/results, with the products limited to ``names`` and no block files."""
    shutil.copytree(ROOT / published.RESULTS, tmp_path / published.RESULTS)
    monkeypatch.setattr(published, "PRODUCTS", tuple(p for p in published.PRODUCTS if p.name in names))
    monkeypatch.setattr(regenerate, "BLOCK_FILES", ())
    monkeypatch.setattr(regenerate, "BLOCKS", {})
    return tmp_path


def test_check_names_the_first_differing_line_and_report_restores_it(tmp_path, monkeypatch, capsys) -> None:
    root = _small_tree(tmp_path, monkeypatch, {"offline summary ant", "online summary online_ip_fast_10seeds"})
    target = root / published.RESULTS / "paper_ant_summary.csv"
    committed = target.read_bytes()
    lines = committed.decode().split("\n")
    lines[2] = lines[2].replace(",10,0,", ",9,0,", 1)  # a drifted n_seeds on line 3
    assert lines[2] != committed.decode().split("\n")[2]
    target.write_text("\n".join(lines))
    assert regenerate.check(root) == [
        f"{published.RESULTS}/paper_ant_summary.csv: line 3: committed {lines[2][:80]!r}, "
        f"generated {committed.decode().split(chr(10))[2][:80]!r}"
    ]
    assert main(["report", "--check", "--root", str(root)]) == EXIT_DIFFERS == 1  # as diff
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "paper_ant_summary.csv: line 3" in err[0] and "1 file(s) differ" in err[0], err
    assert main(["report", "--root", str(root)]) == 0
    assert target.read_bytes() == committed
    assert main(["report", "--check", "--root", str(root)]) == 0


def test_a_missing_output_is_named(tmp_path, monkeypatch) -> None:
    root = _small_tree(tmp_path, monkeypatch, {"online summary online_ip_fast_10seeds"})
    (root / published.RESULTS / "online_ip_fast_10seeds_summary.csv").unlink()
    assert regenerate.check(root) == [f"{published.RESULTS}/online_ip_fast_10seeds_summary.csv: not committed"]


def test_check_names_a_generated_block_removed_with_its_markers_or_its_file(tmp_path, monkeypatch) -> None:
    """A block deleted with its markers (or the page that held it) was never rendered, so never compared: --check
    passed. It is named, as a differing file is."""
    root = _small_tree(tmp_path, monkeypatch, set())
    monkeypatch.setattr(regenerate, "BLOCK_FILES", ("page.md",))
    monkeypatch.setitem(regenerate.BLOCKS, "demo", lambda tree: "| a |\n|---|\n| 1 |\n")
    page = root / "page.md"
    page.write_text("intro\n<!-- report:demo -->\n| a |\n|---|\n| 1 |\n<!-- /report:demo -->\nend\n")
    assert regenerate.check(root) == []
    page.write_text("intro\nend\n")
    missing = ["<!-- report:demo -->: in none of page.md; restore the block with its markers"]
    assert regenerate.check(root) == missing
    assert main(["report", "--check", "--root", str(root)]) == EXIT_DIFFERS
    page.unlink()
    assert regenerate.check(root) == missing


def test_blocks_are_rendered_between_their_markers_only(tmp_path, monkeypatch) -> None:
    monkeypatch.setitem(regenerate.BLOCKS, "demo", lambda tree: "| a |\n|---|\n| 1 |\n")
    text = "before 0.031\n<!-- report:demo -->\nold 0.039\n<!-- /report:demo -->\nafter 0.082\n"
    rendered = regenerate.render_blocks(text, tmp_path)
    assert rendered == "before 0.031\n<!-- report:demo -->\n| a |\n|---|\n| 1 |\n<!-- /report:demo -->\nafter 0.082\n"
    assert regenerate.render_blocks(rendered, tmp_path) == rendered
    with pytest.raises(regenerate.ReportError, match="unknown generated block 'nope'"):
        regenerate.render_blocks("<!-- report:nope -->\n<!-- /report:nope -->\n", tmp_path)
    with pytest.raises(regenerate.ReportError, match="unmatched report markers"):
        regenerate.render_blocks("<!-- report:demo -->\nx\n", tmp_path)


def test_the_docs_hold_the_generated_answer_and_coverage() -> None:
    results = (ROOT / "docs" / "results.md").read_text()
    assert "<!-- report:answer -->\n| env | offline: error gem / delta" in results
    assert "<!-- report:coverage -->" in (ROOT / "docs" / "experiments.md").read_text()


def _committed_results() -> set[str]:
    """Every file of docs/results (a folder of per-run files counts as one entry)."""
    base = ROOT / published.RESULTS
    found = set()
    for path in base.iterdir():
        if path.is_dir() and path.name != "headline":
            found.add(f"{published.RESULTS}/{path.name}")
        elif path.is_dir():
            found |= {f"{published.RESULTS}/headline/{p.name}" for p in path.iterdir()}
        else:
            found.add(f"{published.RESULTS}/{path.name}")
    return found


def test_every_committed_result_is_generated_raw_or_excluded_with_its_reason() -> None:
    outputs = set(published.outputs())
    excluded = set(published.NOT_GENERATED)
    raw = set(published.RAW)
    assert not outputs & excluded and not outputs & raw and not excluded & raw
    assert all(reason.strip() for reason in published.NOT_GENERATED.values())
    unclassified = _committed_results() - outputs - excluded - raw
    assert not unclassified, f"neither generated, per-seed data nor excluded with a reason: {sorted(unclassified)}"
    declared = outputs | excluded | raw | {p for product in published.PRODUCTS for p in product.inputs}
    assert all((ROOT / p).exists() for p in declared), sorted(p for p in declared if not (ROOT / p).exists())


def test_every_study_unit_is_in_the_one_table_and_report_reads_all_of_it() -> None:
    """A study declares what it publishes in its own module (``PUBLICATION``); every such unit is in
    :data:`published.PUBLICATIONS`, and report makes, reads and checks each unit's products, rows, blocks and pages."""
    import importlib

    package = ROOT / "pets" / "experiments"
    declaring = [
        ".".join(path.relative_to(ROOT).with_suffix("").parts)
        for path in sorted(package.rglob("*.py"))
        if "\nPUBLICATION = Publication(" in path.read_text()
    ]
    assert len(declaring) >= 3, declaring  # the gate, the online locomotion and the composition studies at least
    for name in declaring:
        assert importlib.import_module(name).PUBLICATION in published.PUBLICATIONS, f"{name}: not in PUBLICATIONS"
    for unit in published.PUBLICATIONS:
        assert all(p in published.PRODUCTS for p in unit.products), unit.name
        assert set(unit.raw) <= set(published.RAW) and set(unit.not_generated) <= set(published.NOT_GENERATED)
        assert all(regenerate.BLOCKS[name] is render for name, render in unit.blocks.items()), unit.name
        assert set(unit.pages) <= set(regenerate.BLOCK_FILES), unit.name
    names = [unit.name for unit in published.PUBLICATIONS]
    assert len(set(names)) == len(names), names


def test_a_block_name_declared_by_two_studies_is_refused() -> None:
    from pets.experiments.publication import Publication

    twin = Publication("twin", blocks={"composition": lambda tree: ""})
    with pytest.raises(ValueError, match="composition of the study 'twin' are declared twice"):
        regenerate.declared_blocks([*published.PUBLICATIONS, twin])


def test_report_refuses_a_root_without_results(tmp_path, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["report", "--check", "--root", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1 and "no docs/results here" in err[0], err


def test_paper_tables_read_the_committed_summary_cell_by_cell() -> None:
    """Each paper-protocol block: delta's IQM [CI], another model's ratio [CI] and exact p as the summary has them,
    every run past the level spelt out, and no table for a metric the env lacks (zeros)."""
    from pets.experiments.offline_tables import paper_table
    from pets.experiments.report import read_csv_rows

    rows = {
        (r["model"], r["metric"], r["horizon"]): r
        for r in read_csv_rows(ROOT / published.RESULTS / "paper_idp_summary.csv")
    }
    text = paper_table(ROOT, "idp")
    table = [line.split(" | ") for line in text.split("\n") if line.startswith("| ")]
    assert table[0][2:] == ["h=1", "h=5", "h=10", "h=25 |"]  # the horizons the study evaluated
    gem = next(cells for cells in table if cells[1] == "gem")  # the standardized error's row, the first metric
    r = rows[("gem", "standardized_error", "1")]
    assert gem[2] == f"{float(r['ratio_to_delta']):.3g} [{float(r['ratio_ci_low']):.3g}, " + (
        f"{float(r['ratio_ci_high']):.3g}], p {float(r['p_value_exact']):.2g}"
    )
    assert gem[5] == "all diverged |" and rows[("gem", "standardized_error", "25")]["n_seeds"] == "0"
    assert "with n pairs it cannot go below" in text


def test_the_papers_own_comparison_is_the_per_seed_ratio_of_the_committed_runs(tmp_path, monkeypatch) -> None:
    """``paper_own_comparison.csv``: gem2-x1 against delta-det-x1 on Ant is the interquartile mean of the per-seed
    ratios of the committed runs (scipy's trimmed mean), with the exact p of 5 pairs all one way."""
    from scipy.stats import trim_mean

    from pets.experiments.report import read_csv_rows

    root = _small_tree(tmp_path, monkeypatch, {"the paper's own comparison"})
    monkeypatch.chdir(root)
    next(p for p in published.PRODUCTS).make()
    out = read_csv_rows(root / published.RESULTS / "paper_own_comparison.csv")
    row = next(
        r
        for r in out
        if (r["env"], r["model"], r["baseline"], r["metric"], r["horizon"])
        == ("ant", "gem2-x1", "delta-det-x1", "rotation_error", "10")
    )
    runs = read_csv_rows(ROOT / published.RESULTS / "paper_ant_runs.csv")
    value = {(r["model"], r["seed"]): float(r["rotation_error"]) for r in runs if r["horizon"] == "10"}
    ratios = [value[("gem2-x1", s)] / value[("delta-det-x1", s)] for s in "01234"]
    assert float(row["ratio_to_delta"]) == pytest.approx(trim_mean(ratios, 0.25), rel=1e-12)
    assert row["n_pairs"] == "5" and float(row["p_value_exact"]) == pytest.approx(1 / 16)
    assert {r["baseline"] for r in out} == {"delta-det-x1", "delta-det"}


def test_the_versus_table_and_an_env_filtered_table_read_the_committed_files() -> None:
    """The body-frame study's blocks: gem-se / gem per env as its versus file has it (the pairs where gem-se is
    lower), and one env's rows of a summary that holds five."""
    from pets.experiments.offline_tables import GEMSE_METRICS, paper_table, versus_table
    from pets.experiments.report import read_csv_rows

    versus = {r["env"]: r for r in read_csv_rows(ROOT / published.RESULTS / "paper_gemse_primary_versus.csv")}
    lines = versus_table(ROOT, "gemse").split("\n")[2:]
    assert len(lines) == len(versus) == 5
    ant = next(line for line in lines if line.startswith("| ant |"))
    assert ant.endswith(f"| {versus['ant']['n_lower']} of {versus['ant']['n_pairs']} |")
    assert f"{float(versus['ant']['ratio']):.4g} [" in ant
    hopper = paper_table(ROOT, "gemse", env="hopper", metrics=GEMSE_METRICS)
    labels = [line.split(" | ")[0].strip("| ") for line in hopper.split("\n")[2:] if line.startswith("| ")]
    assert [label for label in labels if label] == [m.replace("_", " ") for m in GEMSE_METRICS]
    assert hopper.count("| gem-se |") == len(GEMSE_METRICS)


def test_the_planning_table_reads_the_per_env_summaries_and_the_headlines_holm_step() -> None:
    """HalfCheetah's open loop: gem's difference to delta is the summary's, sign included (prose once had it
    flipped); the closed loop carries Holm's p from the headline; exploratory rows say so."""
    from pets.experiments.report import read_csv_rows
    from pets.experiments.studies.planning import planning_table

    opened = next(
        r for r in read_csv_rows(ROOT / published.RESULTS / "openloop_halfcheetah_summary.csv") if r["model"] == "gem"
    )
    holm = next(
        r["p_value_holm"]
        for r in read_csv_rows(ROOT / published.RESULTS / "headline" / "headline_planning.csv")
        if (r["env"], r["model"], r["loop"]) == ("halfcheetah", "gem", "closed")
    )
    lines = planning_table(ROOT).split("\n")
    cheetah = next(line for line in lines if line.startswith("| halfcheetah | gem |")).split(" | ")
    assert float(opened["diff_to_delta"]) < 0 and cheetah[5].startswith(f"{float(opened['diff_to_delta']):.3g} [")
    assert cheetah[3].endswith(f"Holm {float(holm):.2g}")
    assert sum("(exploratory)" in line for line in lines) == 3


def test_an_online_block_recomputes_its_study_and_holm_spans_the_files_it_joins() -> None:
    """The observation-every-fifth-step study sits in two runs files; its block's Holm step is over both envs
    (the pre-registered family): Reacher's adjusted p is twice its exact p, InvertedDoublePendulum's its own."""
    from pets.experiments.studies.online import study_table

    def p_columns(text: str, env: str) -> tuple[float, float]:
        header = next(line for line in text.split("\n") if line.startswith("| env |")).split(" | ")
        row = next(line for line in text.split("\n") if line.startswith(f"| {env} | gem |")).split(" | ")
        return float(row[header.index("p (sign-flip)")]), float(row[header.index("p (Holm)")])

    joined = study_table(ROOT, ("online_idp_replan5", "online_reacher_replan5"))
    reacher, idp = p_columns(joined, "reacher"), p_columns(joined, "inverteddoublependulum")
    assert reacher[0] < idp[0] and reacher[1] == pytest.approx(2 * reacher[0], rel=1e-2) and idp[1] == idp[0]
    alone = study_table(ROOT, "online_reacher_replan5")
    assert p_columns(alone, "reacher")[1] == p_columns(alone, "reacher")[0]  # one test: nothing to adjust


def test_the_runs_coverage_counts_the_committed_rows() -> None:
    """What ran, per env: Ant's arms with their seed counts as its runs file has them, and an env with no online
    study at the fast preset says so."""
    from pets.experiments.answer import runs_coverage_table
    from pets.experiments.report import read_csv_rows

    seeds: dict[str, set[str]] = {}
    for r in read_csv_rows(ROOT / published.RESULTS / "paper_ant_runs.csv"):
        seeds.setdefault(r["model"], set()).add(r["seed"])
    text = runs_coverage_table(ROOT)
    ant = next(line for line in text.split("\n") if line.startswith("| ant |"))
    assert ant.split(" | ")[1] == ", ".join(f"{m} ({len(s)})" for m, s in seeds.items())
    assert "| hopper |" in text and "not run at the fast preset" in next(
        line for line in text.split("\n") if line.startswith("| hopper |")
    )


def test_report_names_a_committed_input_missing_from_its_root(tmp_path, capsys) -> None:
    """A docs/results without the committed rows (an empty folder) was a FileNotFoundError traceback."""
    (tmp_path / "docs" / "results").mkdir(parents=True)
    with pytest.raises(SystemExit) as exc:
        main(["report", "--check", "--root", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1 and "is missing: report makes its files from a checkout's" in err[0]
