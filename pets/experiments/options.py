"""The ``compare`` command's options (:mod:`pets.experiments.cli` runs them): the modes ``online``, ``offline`` and
``headline``, and the options both run modes share."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pets.experiments.arguments import PROG
from pets.experiments.backend import BACKENDS
from pets.experiments.statistics import MIN_SEEDS
from pets.tools.cli import OneLineParser

#: Seeds of a comparison unless ``--seeds`` says otherwise (the paper's 5).
DEFAULT_SEEDS = ",".join(str(s) for s in range(MIN_SEEDS))


def build_parser() -> OneLineParser:
    """The ``compare`` parser: the modes ``online`` and ``offline`` with their options."""
    p = OneLineParser(
        prog=PROG,
        description="A/B comparison of dynamics heads over envs and seeds, with statistics over seeds "
        "(rliable: IQM, stratified-bootstrap CIs, probability of improvement) and plots (resumable).",
    )
    sub = p.add_subparsers(dest="mode", required=True, parser_class=OneLineParser)

    _add_online(sub)
    _add_offline(sub)
    _add_headline(sub)
    _add_report(sub)
    _add_design(sub)
    return p


def _add_common(q: OneLineParser) -> None:
    """The options of both run modes: what to compare, where, on which backend, with which config."""
    # --envs, --models, --out (and online's --trials) are required unless --config gives them (main checks)
    q.add_argument("--envs", help="comma-separated envs (catalogue names, gymnasium ids or package.module:ATTR)")
    q.add_argument("--models", help="comma-separated models (pets.config.HEADS)")
    q.add_argument(
        "--arm",
        action="append",
        default=[],
        metavar="LABEL=MODEL[:key=value,...]",
        help="one more compared arm: a model with its own overrides, under LABEL (repeatable), e.g. "
        "delta-det-x1=delta-det:model.ensemble_size=1,model.num_elites=1",
    )
    q.add_argument(
        "--seeds",
        default=DEFAULT_SEEDS,
        help=f"comma-separated seeds (default {DEFAULT_SEEDS}; fewer than {MIN_SEEDS} cannot carry a claim)",
    )
    q.add_argument("--out", type=Path, help="output directory (runs, data, summaries)")
    q.add_argument(
        "--backend",
        choices=BACKENDS,
        default="local",
        help="local: a pool of --workers on this machine (default); ray: one Ray task per run (docs/cluster.md)",
    )
    q.add_argument("--workers", type=int, help="local backend: parallel runs (default 1)")
    q.add_argument("--threads", type=int, default=1, help="CPU threads per run (Ray: CPUs per task; default 1)")
    q.add_argument(
        "--address",
        help="ray backend: the cluster (auto, or ray://HOST:10001); default: a new Ray instance on this machine",
    )
    q.add_argument(
        "--max-retries",
        type=int,
        default=3,
        help="ray backend: retries of a run whose worker or node died (default 3; it resumes its checkpoint)",
    )
    q.add_argument(
        "--preset",
        default="research",
        help="config preset: research (default), fast (CPU) or locomotion (a 100k env-step budget per run; "
        "docs/studies/locomotion_gate.md)",
    )
    q.add_argument("--device", choices=("cpu", "cuda", "auto"), default=None, help="device of every run")
    q.add_argument("--quiet", action="store_true", help="no progress bar")
    q.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="a YAML file of config keys for every run (any subset; --print-config writes one); its env, head "
        "and trials stand for --envs, --models and --trials when those are not given; options and key=value "
        "win over it",
    )
    q.add_argument(
        "--print-config",
        action="store_true",
        help="print the settings every run shares, resolved, as YAML (valid as --config) and exit",
    )
    q.add_argument(
        "--estimate",
        action="store_true",
        help="print the CPU-hours of the work still to do in --out (without --out: of all of it), measured on this "
        "machine (online: a few planning and training steps per arm; offline: a few gradient steps per arm and "
        "architecture, a short SAC training), and exit without running or writing anything",
    )
    q.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides for every run")


def _add_online(sub: Any) -> None:
    """The ``online`` mode and its own options."""
    on = sub.add_parser("online", prog=f"{PROG} online", help="online PETS runs (run_pets.py)")
    _add_common(on)
    on.add_argument(
        "--trials",
        type=int,
        help="trials per run (required unless --config or the preset gives trials); with an env-step budget "
        "(max_env_steps, as --preset locomotion sets) the most: each run ends at its budget",
    )
    on.add_argument("--final-window", type=int, default=3, help="trials averaged for the final reward (default 3)")
    on.add_argument(
        "--until-threshold",
        action="store_true",
        help="stop each run at its first trial reaching the env's threshold (pets.experiments.studies.online."
        "THRESHOLDS); --trials is then the most",
    )
    on.add_argument(
        "--planners",
        help="also compare these planners (comma-separated pets.config.PLANNERS); every model x planner pair is an arm",
    )


def _add_offline(sub: Any) -> None:
    """The ``offline`` mode and its own options."""
    off = sub.add_parser("offline", prog=f"{PROG} offline", help="offline training and prediction error")
    _add_common(off)
    off.add_argument("--episodes", type=int, default=100, help="training episodes per env (default 100)")
    off.add_argument(
        "--test-episodes",
        type=int,
        help="test episodes per env (default 20; --protocol paper: 20k samples' worth, ceil(20000 / episode length))",
    )
    off.add_argument("--max-steps", type=int, help="steps per collected episode at most (default: env's length)")
    off.add_argument(
        "--data-seeds",
        default="0",
        help="data sets (comma-separated ints >= 0, default 0): each is collected anew (SAC too) with its own test "
        "set, every model and seed runs on each, and the statistics pair by (data seed, seed), data sets as the "
        "outer level of the bootstrap",
    )
    off.add_argument(
        "--policy",
        default="random",
        help="data policy: random (default), smooth-random[:BETA], sac[:STEPS] (SAC's training transitions; "
        "its agent rolls the test episodes; default STEPS: the protocol's train + validation samples), or "
        "existing (use DIR/data/ENV-{train,test}.npz as they are)",
    )
    off.add_argument(
        "--protocol",
        choices=("pets", "paper"),
        default="pets",
        help="training protocol: pets (bootstrap ensemble, early stopping; default) or paper (the GEM paper's: "
        "100k/10k split, Adam 5e-4, batch 10, 10k iterations, hidden-layer search; pets.data.protocols)",
    )
    off.add_argument("--horizons", default="1,5,10,25,50", help="prediction horizons (default 1,5,10,25,50)")
    off.add_argument("--starts", type=int, default=1000, help="start points of the evaluation (default 1000)")
    off.add_argument("--openloop", action="store_true", help="also plan open loop with every trained model")
    off.add_argument("--planners", default=None, help="open-loop planners (default cem,mppi)")
    off.add_argument("--openloop-steps", type=int, default=None, help="open-loop plan length (default 50)")
    off.add_argument("--openloop-episodes", type=int, default=None, help="open-loop episodes per run (default 5)")
    off.add_argument(
        "--closedloop",
        action="store_true",
        help="also drive MPC with every trained model, frozen (the run's planner per --planners, the open-loop "
        "episodes' seeds; closedloop.csv, paired to delta)",
    )
    off.add_argument("--closedloop-steps", type=int, default=None, help="closed-loop steps per episode (default 300)")
    off.add_argument(
        "--planner-overrides",
        default="",
        metavar="KEY=VALUE,...",
        help="planner.* settings of the open- and closed-loop planning, over each run's own planner (e.g. "
        "planner.population=100,planner.particles=5); recorded, so other settings plan anew",
    )


def _add_headline(sub: Any) -> None:
    """The ``headline`` mode: the per-env answer from earlier comparisons' summaries."""
    head = sub.add_parser(
        "headline",
        prog=f"{PROG} headline",
        help="the per-env answer (each model against delta) from summary.csv files of earlier comparisons",
    )
    head.add_argument("--offline", type=Path, nargs="*", default=[], help="offline summary.csv files")
    head.add_argument("--online", type=Path, nargs="*", default=[], help="online summary.csv files")
    head.add_argument(
        "--relative", type=Path, nargs="*", default=[], help="offline relative_error.csv files (Fig. 2 across envs)"
    )
    head.add_argument("--openloop", type=Path, nargs="*", default=[], help="offline openloop.csv files (planning)")
    head.add_argument(
        "--closedloop", type=Path, nargs="*", default=[], help="offline closedloop.csv files (planning, MPC)"
    )
    head.add_argument(
        "--primary", type=Path, nargs="*", default=[], help="primary.csv files (the pre-registered offline endpoint)"
    )
    head.add_argument("--horizon", type=int, default=50, help="offline horizon (default 50; else the longest below)")
    head.add_argument("--model", default="gem", help="the model whose ratio to delta is plotted (default gem)")
    head.add_argument("--caption", default="", help="a line under the figure, e.g. the machine the runs came from")
    head.add_argument("--out", type=Path, required=True, help="output directory (headline.md, the CSVs)")
    head.add_argument("--figures", type=Path, help="directory of the figures (default: --out)")


def _add_report(sub: Any) -> None:
    """The ``report`` mode: published tables from committed per-seed rows (:mod:`pets.experiments.regenerate`)."""
    rep = sub.add_parser(
        "report",
        prog=f"{PROG} report",
        help="regenerate docs/results' summaries and the docs' generated blocks from the committed per-seed rows",
    )
    rep.add_argument("--check", action="store_true", help="write nothing; exit 1 if any committed file differs")
    rep.add_argument("--root", type=Path, default=Path("."), help="the repository root (default: .)")


def _add_design(sub: Any) -> None:
    """The ``design`` mode: the studies' registered jobs as commands (:mod:`pets.experiments.design`)."""
    des = sub.add_parser(
        "design",
        prog=f"{PROG} design",
        help="print a study's registered jobs (every one, or those its committed rows lack) as commands to run",
    )
    des.add_argument("studies", nargs="*", metavar="STUDY", help="the studies (default: every study with a design)")
    des.add_argument("--left", action="store_true", help="only the jobs the committed rows do not complete")
    des.add_argument("--runs", type=Path, default=Path("runs"), help="the folder of the runs (default: runs)")
    des.add_argument("--root", type=Path, default=Path("."), help="the repository root (default: .)")
