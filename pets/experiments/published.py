"""What ``pets.compare report`` publishes: the one table of the studies' units (:data:`PUBLICATIONS`, each a
:class:`pets.experiments.publication.Publication`: a study's committed per-seed rows, the files made from them, the
doc blocks rendered from those and the committed summaries it does not make, each with why), and the units of the
studies made before a study declared its own in its module (the offline, online and planning studies, the
headline). Everything report makes and checks is read from :data:`PUBLICATIONS`: :data:`PRODUCTS`, :data:`RAW`,
:data:`NOT_GENERATED` and (in :mod:`pets.experiments.regenerate`) the blocks. A new study declares ``PUBLICATION``
in its own module and adds one line to :data:`PUBLICATIONS`. Paths are relative to the repository root; the
products run with that root (or a copy of its docs/results) as the working directory.

The code is the code that made the committed files: :func:`pets.experiments.studies.offline.summary_from_runs`
(``docs/scripts/resummarise_offline.py``), :func:`pets.experiments.studies.primary.write_primary_files`
(``docs/scripts/offline_primary.py``), :func:`pets.experiments.studies.online.summary_from_runs` (the statistics of
``pets.compare online``) and :func:`pets.experiments.headline.write_headline` (``pets.compare headline``).
"""

from __future__ import annotations

import csv
import functools
from collections.abc import Sequence
from pathlib import Path

from pets.experiments import gate_published, offline_tables
from pets.experiments.design import Design
from pets.experiments.publication import RESULTS as RESULTS  # re-exported: answer.py and the tests read it here
from pets.experiments.publication import Product, Publication, results_path
from pets.experiments.report import read_csv_rows
from pets.experiments.studies import composition, locomotion
from pets.experiments.studies.online import study_table
from pets.experiments.studies.planning import ENVS as PLANNING_ENVS
from pets.experiments.studies.planning import planning_table
from pets.experiments.studies.primary import DEFAULT_LEVEL, DEFAULT_SOURCE

#: The no-information level of each env's data set, computed from the data sets (not in the repository) by the
#: studies that made them anew (``primary.csv``'s ``level``; InvertedPendulum's also for its original study).
DATA_LEVELS = {
    "ant": 1.2823407726495033,
    "reacher": 1.3067071711948632,
    "inverteddoublependulum": 0.876485780322665,
    "invertedpendulum": 1.126818220138612,
    "halfcheetah": 1.3950981719691522,
    "hopper": 1.4547009136555746,
    "walker2d": 1.3986959520628426,
    "humanoid": 1.3946240754991805,
}
#: The original offline studies (one data set each), in the order of the headline's command.
ORIGINAL = ("reacher", "ant", "idp", "halfcheetah", "hopper", "walker2d", "humanoid", "ip")
#: The same in the order of the primary endpoint's command (docs/results.md), which is its rows' order.
PRIMARY_ORDER = ("idp", "reacher", "ant", "halfcheetah", "hopper", "walker2d", "humanoid", "ip")
#: The online studies whose summary report makes from their committed per-run rows.
ONLINE = (
    "online_ip_fast_10seeds",
    "online_reacher_fast_5seeds",
    "online_idp_fast_5seeds",
    "online_halfcheetah_fast_5seeds",
    "online_ant_fast",
    "activation_reacher_fast_5seeds",
    "time_to_solve_halfcheetah",
    "time_to_solve_halfcheetah_compiled",
    "time_to_solve_ip_compiled",
    "time_to_solve_reacher_compiled",
)


def _levels(envs: Sequence[str], data: bool) -> dict[str, tuple[float, str]]:
    """{env: (level, source)}: the data sets' levels (``data``) or sqrt(2) where the data are not at hand."""
    if not data:
        return dict.fromkeys(envs, (DEFAULT_LEVEL, DEFAULT_SOURCE))
    return {e: (DATA_LEVELS[e], f"data ({e}-train.npz vs {e}-test.npz)") for e in envs}


def _offline_summary(study: str, data_levels: bool, relative: bool = True) -> Product:
    """``paper_STUDY_summary.csv`` (and ``_relative_error.csv``) from ``paper_STUDY_runs.csv``, env by env at its
    level (``docs/scripts/resummarise_offline.py``)."""
    runs = results_path(f"paper_{study}_runs.csv")
    names = ("summary", "relative_error") if relative else ("summary",)
    outputs = tuple(results_path(f"paper_{study}_{name}.csv") for name in names)

    def make() -> None:
        from pets.experiments.report import write_csv
        from pets.experiments.studies.offline import RELATIVE_COLUMNS, SUMMARY_COLUMNS, summary_from_runs

        rows = read_csv_rows(runs)
        envs = list(dict.fromkeys(r["env"] for r in rows))
        levels = _levels(envs, data_levels or study == "ip")
        summary, rel = [], []
        for env in envs:
            s, r = summary_from_runs([x for x in rows if x["env"] == env], levels[env][0])
            summary, rel = summary + s, rel + r
        write_csv(Path(outputs[0]), summary, SUMMARY_COLUMNS)
        if relative:
            write_csv(Path(outputs[1]), rel, RELATIVE_COLUMNS)

    return Product(f"offline summary {study}", outputs, (runs,), make)


#: The paper's own comparison: GEM's deterministic models against the baseline's of the same kind (model, baseline).
OWN_PAIRS = (("gem2-x1", "delta-det-x1"), ("gem2", "delta-det"))


def _own_comparison() -> Product:
    """``paper_own_comparison.csv``: per original study and :data:`OWN_PAIRS` pair (where the study ran both), the
    offline summary's comparison of the model with that baseline in place of delta (``baseline`` names it)."""
    inputs = tuple(results_path(f"paper_{s}_runs.csv") for s in ORIGINAL)
    out = results_path("paper_own_comparison.csv")

    def make() -> None:
        from pets.experiments.report import write_csv
        from pets.experiments.statistics import BASELINE
        from pets.experiments.studies.offline import SUMMARY_COLUMNS, summary_from_runs

        table = []
        for study, path in zip(ORIGINAL, inputs, strict=True):
            rows = read_csv_rows(path)
            level = _levels([rows[0]["env"]], study == "ip")[rows[0]["env"]][0]
            for model, baseline in OWN_PAIRS:
                pair = [{**r, "model": BASELINE if r["model"] == baseline else model} for r in rows
                        if r["model"] in (model, baseline)]  # fmt: skip
                if {r["model"] for r in pair} == {model, BASELINE}:
                    summary, _ = summary_from_runs(pair, level)
                    table += [{**r, "baseline": baseline} for r in summary if r["model"] == model]
        write_csv(Path(out), table, ["baseline", *SUMMARY_COLUMNS])

    return Product("the paper's own comparison", (out,), inputs, make)


def _per_data_set() -> Product:
    """``paper_data3_per_data_set.csv``: the primary endpoint of each of the 3-data-set study's data sets alone
    (:func:`pets.experiments.studies.primary.per_data_set_rows`), at the data sets' levels."""
    runs, out = results_path("paper_data3_runs.csv"), results_path("paper_data3_per_data_set.csv")

    def make() -> None:
        from pets.experiments.report import write_csv
        from pets.experiments.studies.primary import PER_DATA_SET_COLUMNS, per_data_set_rows

        rows = read_csv_rows(runs)
        levels = _levels(list(dict.fromkeys(r["env"] for r in rows)), True)
        write_csv(Path(out), per_data_set_rows(rows, levels), PER_DATA_SET_COLUMNS)

    return Product("the 3-data-set study per data set", (out,), (runs,), make)


def _primary(
    out: str, studies: Sequence[str], *, data_levels: bool, models: set[str] | None = None, **files: str
) -> Product:
    """The primary endpoint of ``paper_STUDY_runs.csv`` files (``docs/scripts/offline_primary.py``): ``OUT.csv`` and
    the past-level file, the versus file with ``versus=`` (file names as committed: ``past_level=``, ``versus=``;
    ``past_level=""``: the study never committed one; ``primary=""``: ``OUT.csv`` is made but not published)."""
    inputs = tuple(results_path(f"paper_{s}_runs.csv") for s in studies)
    past = results_path(files.get("past_level") or f"{out}_past_level.csv")
    versus = results_path(files["versus"]) if "versus" in files else None
    published = () if files.get("past_level") == "" else (past,)  # "": made, never committed, so not an output
    primary = () if files.get("primary") == "" else (results_path(f"{out}.csv"),)  # "": made, excluded (NOT_GENERATED)
    outputs = (*primary, *published, *((versus,) if versus else ()))

    def make() -> None:
        from pets.experiments.studies.primary import write_primary_files

        keep = None if models is None else {"delta", *models}
        rows = [r for path in inputs for r in read_csv_rows(path) if keep is None or r["model"] in keep]
        envs = list(dict.fromkeys(r["env"] for r in rows))
        levels = _levels(envs, True) if data_levels else {}
        comparisons = [("gem-se", "gem")] if versus else []
        write_primary_files(rows, results_path(out), levels, comparisons, past_level=past, versus=versus)

    return Product(f"primary {out}", outputs, inputs, make)


def _committed_columns(path: str, default: Sequence[str]) -> list[str]:
    """The header of the committed file (older studies keep the columns of their date), else ``default``."""
    if not Path(path).is_file():
        return list(default)
    with open(path, newline="") as f:
        return next(csv.reader(f))


def _online_summary(study: str) -> Product:
    """``STUDY_summary.csv`` from ``STUDY_runs.csv`` (the statistics of ``pets.compare online``), with the columns
    the committed file has (columns added since, such as the exact p of older studies, are not written)."""
    runs, out = results_path(f"{study}_runs.csv"), results_path(f"{study}_summary.csv")

    def make() -> None:
        from pets.experiments.report import write_csv
        from pets.experiments.studies.online import SUMMARY_COLUMNS, summary_from_runs

        write_csv(Path(out), summary_from_runs(read_csv_rows(runs)), _committed_columns(out, SUMMARY_COLUMNS))

    return Product(f"online summary {study}", (out,), (runs,), make)


def _headline() -> Product:
    """docs/results/headline (``pets.compare headline`` with docs/results.md's command) and its figures."""
    offline = [results_path(f"paper_{e}_summary.csv") for e in ORIGINAL]
    relative = [results_path(f"paper_{e}_relative_error.csv") for e in ORIGINAL]
    online = [results_path(f"{s}_summary.csv") for s in ONLINE[:4]]
    openloop = [results_path(f"openloop_{e}_summary.csv") for e in PLANNING_ENVS]
    closedloop = [results_path(f"planning_{e}_summary.csv") for e in PLANNING_ENVS]
    primary = [results_path("offline_primary_gem.csv"), results_path("paper_gemse_primary.csv")]
    names = ("headline.md", "headline_offline.csv", "headline_online.csv", "headline_planning.csv")
    figures = ("headline_ratio.png", "headline_relative.png", "headline_fig2_ratio.png")
    outputs = (*(results_path(f"headline/{n}") for n in names), *(f"docs/figures/{n}" for n in figures))

    def make() -> None:
        from pets.experiments.headline import write_headline

        write_headline(
            *([Path(p) for p in paths] for paths in (offline, online)),
            Path(results_path("headline")),
            caption="runs: AMD EPYC Zen 4, one thread per run",
            relative=[Path(p) for p in relative],
            figures=Path("docs/figures"),
            openloop=[Path(p) for p in openloop],
            closedloop=[Path(p) for p in closedloop],
            primary=[Path(p) for p in primary],
        )

    inputs = (*offline, *relative, *online, *openloop, *closedloop, *primary)
    return Product("headline", outputs, inputs, make)


_CRLF = "written with CRLF line ends by the CSV writer of its date; today's code gives the same values with LF ends"
_PLANNING = (
    "the planning study's per-seed results (open and closed loop) are not committed, only its summaries, so they "
    "cannot be regenerated (and its p-values not recomputed) from docs/results"
)
_PEER_SUMMARY = "docs/scripts/peer_mbrl.py summarise (CRLF line ends); not in report"
_GEMSE_ENVS = ("halfcheetah", "hopper", "walker2d", "ant", "humanoid")

#: The planning study (docs/results.md, "Planning"): its summaries only are committed.
PLANNING = Publication(
    "planning",
    blocks={"planning": planning_table},
    not_generated={
        **{
            results_path(f"{kind}_{e}{ext}"): _PLANNING
            for kind in ("openloop", "planning")
            for e in PLANNING_ENVS
            for ext in (".md", "_summary.csv")
        },  # fmt: skip
        results_path("planning_walker2d_cem.md"): _PLANNING,
        results_path("planning_walker2d_cem_summary.csv"): _PLANNING,
    },
)
#: The offline studies of the paper's protocol: the original 8, the 3-data-set, 50k and gem-se studies.
OFFLINE = Publication(
    "offline",
    raw=(
        *(
            results_path(f"paper_{s}_runs.csv")
            for s in (*ORIGINAL, "data3", "50k", "gemse", "gemse_partial", "idp_h50")
        ),
        results_path("learning_curves_50k.csv"),
        results_path("learning_curves_paper.csv"),
    ),
    products=(
        *(_offline_summary(e, data_levels=False) for e in ORIGINAL),
        _own_comparison(),
        _offline_summary("data3", data_levels=True),
        _per_data_set(),
        _offline_summary("50k", data_levels=True),
        _offline_summary("gemse_partial", data_levels=True, relative=False),
        _primary("offline_primary_gem", PRIMARY_ORDER, data_levels=False, models={"gem"}),
        _primary("offline_primary_all_arms", PRIMARY_ORDER, data_levels=False),
        _primary("paper_data3_primary", ["data3"], data_levels=True, past_level="paper_data3_past_level.csv"),
        _primary("paper_50k_primary", ["50k"], data_levels=True, past_level="paper_50k_past_level.csv"),
        _primary("paper_gemse_primary", ["gemse"], data_levels=True, versus="paper_gemse_primary_versus.csv"),
        _primary("paper_ip_primary", ["ip"], data_levels=True, primary="", past_level="paper_ip_past_level.csv"),
        _primary(
            "paper_gemse_partial_primary",
            ["gemse_partial"],
            data_levels=True,
            past_level="",
            versus="paper_gemse_partial_versus.csv",
        ),
    ),
    blocks={
        **{f"offline-paper-{s}": functools.partial(offline_tables.paper_table, study=s) for s in ORIGINAL},
        "offline-paper-own": offline_tables.own_comparison_table,
        "offline-gemse-versus": functools.partial(offline_tables.versus_table, study="gemse"),
        **{
            f"offline-gemse-{e}": functools.partial(
                offline_tables.paper_table, study="gemse", env=e, metrics=offline_tables.GEMSE_METRICS
            )
            for e in _GEMSE_ENVS
        },
        "offline-data-sets": offline_tables.data_sets_table,
        "offline-learning-curves": offline_tables.curves_table,
    },
    not_generated={
        results_path("paper_gemse_summary.csv"): _CRLF,
        results_path("paper_ip_primary.csv"): (
            "written by pets.compare offline before the ci_exact_note column; today's code gives the same values "
            "and that column (its past-level file is generated)"
        ),
        results_path("paper_idp_h50_per_horizon.csv"): (
            "per-horizon statistics in an older column set (p_ci_low, no n_diverged or exact p) by a command not "
            "kept in the repository; its per-run rows (paper_idp_h50_runs.csv) are committed"
        ),
        results_path(
            "onestep_before_issue18.csv"
        ): "one-step errors per dimension of trained models that are not committed",
        results_path(
            "onestep_after_issue18.csv"
        ): "one-step errors per dimension of trained models that are not committed",
    },
)
_REPLAN5 = ("online_idp_replan5", "online_reacher_replan5")
#: The online studies at the fast presets, their ablations and the time-to-solve studies; mbrl-lib beside them.
ONLINE_FAST = Publication(
    "online (fast presets)",
    raw=(
        *(results_path(f"{s}_runs.csv") for s in (*ONLINE, *_REPLAN5)),
        *(results_path(f"{s}_runs.csv") for s in ("time_to_solve_ip", "time_to_solve_reacher")),
        *(results_path(f"{s}_runs.csv") for s in ("ip_fast_5seeds", "ip_fast_ablation", "ip_fast_diagnosis")),
        *(results_path(f"{s}_runs.csv") for s in ("ip_fast_value", "idp_feedback_ablation", "idp_feedback_fast")),
        results_path("online_ant_metrics"),
        results_path("online_replan5_metrics"),
        results_path("time_to_solve_halfcheetah_compiled_metrics"),
        results_path("peer_learning_invertedpendulum.csv"),
        results_path("peer_learning_reacher.csv"),
        results_path("peer_planning_step.csv"),
    ),
    products=tuple(_online_summary(s) for s in ONLINE),
    blocks={
        **{f"online-{s}": functools.partial(study_table, study=s) for s in ONLINE if "time_to_solve" not in s},
        "online-replan5": functools.partial(study_table, study=_REPLAN5),
    },
    not_generated={
        results_path("online_idp_replan5_summary.csv"): _CRLF,
        results_path("online_reacher_replan5_summary.csv"): _CRLF,
        **{results_path(f"peer_learning_{e}_summary.csv"): _PEER_SUMMARY for e in ("invertedpendulum", "reacher")},
    },
)
#: The headline across the studies (``pets.compare headline``).
HEADLINE = Publication("headline", products=(_headline(),))

#: Every study's unit, in the order report makes their products (a product's inputs are made before it).
PUBLICATIONS: tuple[Publication, ...] = (
    PLANNING,
    OFFLINE,
    ONLINE_FAST,
    HEADLINE,
    gate_published.PUBLICATION,
    locomotion.PUBLICATION,
    composition.PUBLICATION,
)
#: Every generated file's product, in the order they are made.
PRODUCTS: tuple[Product, ...] = tuple(p for unit in PUBLICATIONS for p in unit.products)
#: Committed summaries report does not make, each with why (``report --check`` names them, never skips silently).
NOT_GENERATED: dict[str, str] = {path: why for unit in PUBLICATIONS for path, why in unit.not_generated.items()}
#: Committed per-seed (or per-trial) data: what summaries are made from, nothing to regenerate.
RAW: tuple[str, ...] = tuple(path for unit in PUBLICATIONS for path in unit.raw)
#: The registered work of the studies that declare it (:mod:`pets.experiments.design`): what runs, in what order,
#: from which commit, and what their committed rows lack (``docs/scripts/study_jobs.py`` queues it).
DESIGNS: tuple[Design, ...] = (gate_published.DESIGN, locomotion.DESIGN, composition.DESIGN)


def outputs() -> list[str]:
    """Every file the products make, in order."""
    return [path for product in PRODUCTS for path in product.outputs]
