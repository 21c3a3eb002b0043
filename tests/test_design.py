"""The studies' registered designs (pets.experiments.design): what each runs, in what order, from which commit, and
what its committed rows lack. Ground truth: the committed rows themselves, the config system (make_config), the
commands' own parsers, and the pre-registered numbers in the study pages (seeds, data sets, pairs, arms)."""

import csv
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from pets.experiments import gate_published
from pets.experiments.design import Design, Job
from pets.experiments.published import DESIGNS
from pets.experiments.studies import composition, locomotion

ROOT = Path(__file__).resolve().parents[1]
STUDY_JOBS = ROOT / "docs" / "scripts" / "study_jobs.py"


def rows(name: str) -> list[dict[str, str]]:
    with open(ROOT / "docs" / "results" / name, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.parametrize("design", DESIGNS, ids=lambda d: d.name)
def test_a_designs_jobs_are_unique_and_what_is_left_keeps_their_order(design: Design):
    jobs = list(design.jobs(ROOT))
    names = [job.name for job in jobs]
    assert jobs and len(set(names)) == len(names)
    left = list(design.left(ROOT))
    assert [job for job in jobs if job in left] == left  # the same jobs, in the registered order
    assert len(design.commit) >= 7 and int(design.commit, 16) >= 0 and design.issue > 0


def test_every_module_that_declares_a_design_is_in_the_table():
    import importlib

    package = ROOT / "pets" / "experiments"
    declaring = [
        ".".join(path.relative_to(ROOT).with_suffix("").parts)
        for path in sorted(package.rglob("*.py"))
        if "\nDESIGN = Design(" in path.read_text()
    ]
    assert len(declaring) == len(DESIGNS) >= 3, declaring  # the gate's ablation, the online and composition studies
    for name in declaring:
        assert importlib.import_module(name).DESIGN in DESIGNS, f"{name}: not in published.DESIGNS"
    assert len({d.name for d in DESIGNS}) == len(DESIGNS)


def test_every_job_is_a_command_its_parser_accepts():
    """run_pets.py's and pets.compare's own parsers take every registered job's arguments (``{out}`` resolved)."""
    import run_pets
    from pets.experiments.cli import _parse, build_parser

    for design in DESIGNS:
        for job in design.jobs(ROOT):
            args = shlex.split(job.command(Path("/runs")))
            if job.kind == "pets":
                parsed = run_pets.build_parser().parse_args([a for a in args if "=" not in a])
                assert parsed.env and parsed.model and parsed.preset == "locomotion", job
            else:
                assert args[:3] == ["python", "-m", "pets.compare"]
                parsed = _parse(build_parser(), args[3:])
                assert parsed.mode == "offline" and str(parsed.out) == f"/runs/{job.folder}/results", job


def test_a_job_of_an_unknown_kind_is_refused():
    with pytest.raises(ValueError, match="kind must be one of pets, compare, got 'slurm'"):
        Job("x", 0, "runs", "slurm", ())


def test_the_ablation_arms_record_their_overrides_as_a_pilot_row_does():
    """A pilot row names its arm by the keys where its config differs from the preset, written ``key=value`` with
    the config's value: each arm's command-line overrides give exactly its recorded spelling."""
    from omegaconf import OmegaConf

    from pets.config import make_config, parse_overrides

    for _, overrides, recorded, _ in gate_published.ABLATION_ARMS:
        given = parse_overrides(overrides.split())
        cfg = make_config("halfcheetah", "delta", "locomotion", given)
        assert " ".join(f"{key}={OmegaConf.select(cfg, key)}" for key in given) == recorded
    jobs = gate_published.DESIGN.jobs(ROOT)
    assert [job.seed for job in jobs] == [100] * 3 + [101] * 3 + [102] * 3  # seed-major: 3 arms x 3 seeds


def test_the_composition_design_is_3_data_sets_x_5_seeds_of_every_arm_on_both_bodies():
    jobs = composition.DESIGN.jobs(ROOT)
    cells = set()
    for job in jobs:
        args = job.args
        env, models = args[args.index("--envs") + 1], args[args.index("--models") + 1].split(",")
        for model in models:
            cells.add((env, model, int(args[args.index("--data-seeds") + 1]), int(args[args.index("--seeds") + 1])))
    for env in ("ant", "humanoid"):
        for model in ("delta-groupfeat", "gem", "gem-se", "delta"):
            assert len({(d, s) for e, m, d, s in cells if (e, m) == (env, model)}) == composition.PAIRS == 15


def test_composition_left_is_every_seed_of_each_data_set_the_committed_rows_lack():
    from pets.experiments.offline_data import data_paths

    done = {(r["env"], r["model"], r["data"], int(r["seed"])) for r in rows(composition.RUNS)}
    left = {job.name for job in composition.DESIGN.left(ROOT)}
    for env in ("ant", "humanoid"):
        for d in (0, 1, 2):
            test_file = data_paths(Path(), env, d)[1].name
            missing = any((env, m, test_file, s) not in done for m in composition.MODELS for s in range(5))
            assert (
                {f"{env}-d{d}-s{s}" for s in range(5)} <= left
                if missing
                else not any(name.startswith(f"{env}-d{d}-") for name in left)
            )


def test_the_online_study_runs_where_the_gate_passed_and_delta_groupfeat_only_off_planar_bodies(tmp_path):
    results = tmp_path / "docs" / "results"
    results.mkdir(parents=True)
    summary = "env,agent,verdict\nhalfcheetah,delta,passed\nant,delta,passed\nhopper,delta,not passed\n"
    (results / locomotion.GATE_SUMMARY).write_text(summary)
    (results / locomotion.RUNS).write_text(",".join(locomotion.RUN_COLUMNS) + "\n")
    jobs = locomotion.DESIGN.left(tmp_path)
    arms = {env: {j.args[3] for j in jobs if j.args[1] == env} for env in ("halfcheetah", "ant", "hopper")}
    assert arms == {
        "halfcheetah": {"gem-se", "gem", "delta"},  # planar: delta-groupfeat is gem's run
        "ant": {"gem-se", "gem", "delta-groupfeat", "delta"},
        "hopper": set(),  # the gate did not pass there
    }
    assert [j.seed for j in jobs] == sorted(j.seed for j in jobs) and {j.seed for j in jobs} == set(range(10))


def test_study_jobs_lists_each_run_the_committed_rows_lack_once_in_queue_format(tmp_path: Path):
    """docs/scripts/study_jobs.py: every online-study (arm, seed) without a complete committed row is queued exactly
    once over the two files, no complete one is; every line is WORKDIR|OUT|KIND|ARGS; --write never overwrites."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("study_jobs", STUDY_JOBS)
    jobs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(jobs)
    core1, core2 = jobs.queues(tmp_path, Path("/wt/gate"), Path("/wt/comp"))
    lines = [line for line in core1 + core2 if not line.startswith("#")]
    assert all(len(line.split("|")) == 4 and line.split("|")[2] in ("pets", "cmd") for line in lines)
    complete = {(r["model"], r["seed"]) for r in rows(locomotion.RUNS) if r["status"] == "complete"}
    queued = [line.split("|")[1].rsplit("/", 1)[1] for line in lines if "/online/" in line]
    assert len(queued) == len(set(queued))
    arms = ("gem-se", "gem", "delta")  # on planar HalfCheetah, delta-groupfeat takes gem's run
    expected = {f"halfcheetah-{a}-s{s}" for s in range(10) for a in arms if (a, str(s)) not in complete}
    assert set(queued) == expected and "halfcheetah-gem-se-s0" not in queued
    assert all(line.startswith("/wt/gate|") for line in lines if "/online/" in line or "/pilots/" in line)
    (tmp_path / "next_core1.jobs").write_text("# a running queue's file\n")
    args = ["--runs", str(tmp_path), "--gate-worktree", "/wt/gate", "--composition-worktree", "/wt/comp", "--write"]
    done = subprocess.run([sys.executable, str(STUDY_JOBS), *args], capture_output=True, text=True)
    assert done.returncode != 0 and "exists (a queue may be reading it)" in done.stderr
    assert (tmp_path / "next_core1.jobs").read_text() == "# a running queue's file\n"


def test_study_jobs_refuses_a_worktree_not_at_the_studys_commit(tmp_path: Path):
    """A study runs from its pinned commit: a worktree checked out elsewhere (this checkout) or no git worktree at
    all is one line naming the commit and how to make the worktree, exit 1, no file written."""
    for gate_wt, comp_wt, found in ((ROOT, ROOT, "is at "), (tmp_path, tmp_path, "not a git worktree")):
        args = ["--runs", str(tmp_path), "--gate-worktree", str(gate_wt), "--composition-worktree", str(comp_wt)]
        done = subprocess.run([sys.executable, str(STUDY_JOBS), *args], capture_output=True, text=True)
        assert done.returncode == 1 and found in done.stderr, done.stderr
        assert f"git worktree add --detach {gate_wt} {gate_published.DESIGN.commit}" in done.stderr
        assert len(done.stderr.strip().splitlines()) == 1 and not list(tmp_path.glob("*.jobs"))


def test_pets_compare_design_prints_a_studys_jobs_or_those_left_as_commands(capsys):
    from pets.experiments.cli import main

    assert main(["design", "composition", "--left", "--runs", "/r", "--root", str(ROOT)]) == 0
    head, *lines = capsys.readouterr().out.strip().splitlines()
    left = composition.DESIGN.left(ROOT)
    assert head.startswith(f"# composition (issue 53): 30 registered jobs, {len(left)} not complete")
    assert f"git worktree add --detach ../wt-composition {composition.DESIGN.commit}" in head
    assert lines == [job.shell_line(Path("/r")) for job in left]
    assert main(["design", "--root", str(ROOT)]) == 0
    out = capsys.readouterr().out
    assert [line.split(" (issue")[0][2:] for line in out.splitlines() if line.startswith("# ")] == [
        d.name for d in DESIGNS
    ]
    assert "python run_pets.py --env halfcheetah --model gem-se --preset locomotion --seed 9 threads=1 --out " in out
    assert main(["design", "online-locomotion", "--runs", "/my runs", "--root", str(ROOT)]) == 0
    line = capsys.readouterr().out.splitlines()[-1]  # a folder with a space: each path one word of the shell line
    assert shlex.split(line)[-2:] == ["--out", "/my runs/online/halfcheetah-delta-s9"]


def test_pets_compare_design_refuses_an_unknown_study_or_root_in_one_line(tmp_path, capsys):
    from pets.experiments.cli import main

    for argv, fragment in (
        (["design", "nope", "--root", str(ROOT)], "no study named 'nope' has a design; accepted: locomotion-gate"),
        (["design", "--root", str(tmp_path)], f"{tmp_path} has no docs/results"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert exit_info.value.code == 2 and len(err) == 1 and fragment in err[0], err


def test_a_reader_that_closes_the_pipe_early_gets_no_error_line():
    """``pets.compare design | head -1``: the reader goes away before the listing is written; no traceback and no
    'writing a file failed' line (nothing of the command's own failed), exit 1 as Python does on EPIPE."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "pets.compare", "design"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    proc.stdout.close()  # before the command has imported anything: its first write meets a closed pipe
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 1 and err == ""


@pytest.mark.parametrize("design", DESIGNS, ids=lambda d: d.name)
def test_each_design_has_a_generated_progress_block_on_a_study_page(design: Design):
    """A study page never types how far its study has got: a report block renders it from the committed rows."""
    from pets.experiments import regenerate

    (name,) = [n for n, render in regenerate.BLOCKS.items() if render == design.progress]
    assert any(f"<!-- report:{name} -->" in (ROOT / page).read_text() for page in regenerate.BLOCK_FILES)
    text = design.progress(ROOT)
    jobs, left = design.jobs(ROOT), design.left(ROOT)
    assert f"**{len(jobs) - len(left)} of {len(jobs)}**" in text and f"`{design.commit}`" in text
    assert [part.strip(" `.") for part in text.split("registered order: ")[1].split(",")] == (
        [job.name for job in left] or ["none"]
    )
