"""summary.md of ``pets.compare online`` names what a reviewer needs to redo the comparison: the seeds, the command
that wrote it and the machines its runs ran on (from each run's history.csv)."""

from __future__ import annotations

import csv
import socket

import numpy as np
import scipy.stats

from pets.experiments.cli import command_line
from pets.experiments.studies.online import summarise_online
from pets.runs import rundir
from pets.runs.hardware import cpu_name


def _run(out, model, seed, rewards):
    run = out / "runs" / f"reacher-{model}-s{seed}"
    run.mkdir(parents=True)
    lines = ["trial,env_steps,episode_reward,wall_time_s,plan_seconds_per_step"]
    lines += [f"{t},{100 * (t + 1)},{r!r},{10.0 * (t + 1)},0.1" for t, r in enumerate(rewards)]
    (run / "metrics.csv").write_text("\n".join(lines) + "\n")
    return run


def test_summary_md_names_the_seeds_the_command_and_the_machines(tmp_path):
    for model, bonus in (("delta", 0.0), ("gem", 2.0)):
        for seed in (3, 7, 8):
            run = _run(tmp_path, model, seed, [seed + bonus + t for t in range(3)])
            rundir.append_history(run, "start", 0)
    # a run resumed on another machine counts on each of its machines
    history = tmp_path / "runs" / "reacher-gem-s8" / "history.csv"
    history.write_text(history.read_text() + "2026-01-01T00:00:00,resume,1,otherhost,1,Other CPU\n")
    command = command_line(["online", "--envs", "reacher", "--seeds", "3,7,8", "--out", "my dir"])
    assert command == "python -m pets.compare online --envs reacher --seeds 3,7,8 --out 'my dir'"
    summarise_online(tmp_path, ["reacher"], ["delta", "gem"], [3, 7, 8], 3, 2, reps=50, command=command)
    md = (tmp_path / "summary.md").read_text()
    assert "- seeds: 3, 7, 8 (3; an arm's run is paired with delta's run of the same seed)" in md
    assert f"- command: `{command}`" in md
    here = f"{socket.gethostname()} ({cpu_name()}): 6 runs"
    assert "- machines (runs/RUN/history.csv): " in md and here in md
    assert "otherhost (Other CPU): 1 run" in md and "1 runs" not in md
    # without a command (the library called directly) and runs without a history: said, not guessed
    for run in (tmp_path / "runs").iterdir():
        (run / "history.csv").unlink()
    summarise_online(tmp_path, ["reacher"], ["delta", "gem"], [3, 7, 8], 3, 2, reps=50)
    md = (tmp_path / "summary.md").read_text()
    assert "- command:" not in md and "- machines (runs/RUN/history.csv): not recorded" in md


def test_summary_md_says_the_sign_flip_p_is_two_sided_and_it_is(tmp_path):
    finals = {"delta": [5.0, 1.0, 4.0, 2.0, 3.0], "gem": [6.0, 3.0, 4.5, 5.0, 2.5]}
    for model, values in finals.items():
        for seed, v in enumerate(values):
            _run(tmp_path, model, seed, [0.0, v])
    summarise_online(tmp_path, ["reacher"], ["delta", "gem"], range(5), 2, 1, reps=50)
    diff = np.subtract(finals["gem"], finals["delta"])
    two_sided = scipy.stats.permutation_test(
        (diff,), np.mean, permutation_type="samples", n_resamples=np.inf, alternative="two-sided"
    ).pvalue
    with open(tmp_path / "summary.csv", newline="") as f:
        gem = next(r for r in csv.DictReader(f) if r["model"] == "gem")
    assert float(gem["diff_p_signflip"]) == two_sided == 0.1875  # one-sided (greater) would be 0.09375
    assert "p (sign-flip): the exact two-sided paired permutation p-value" in (tmp_path / "summary.md").read_text()
