"""The locomotion gate's endpoint and verdict (pets.experiments.gate; docs/studies/locomotion_gate.md)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from pets.experiments import gate
from pets.experiments.report import write_rounded_csv
from tests import warm


def episode(steps: int, reward: float, length: int, terminated: bool = False) -> dict[str, str]:
    return {"env_steps": str(steps), "episode_reward": str(reward), "episode_length": str(length),
            "terminated": str(int(terminated))}  # fmt: skip


def test_the_endpoint_is_the_last_five_complete_episodes_and_skips_one_cut_by_the_budget():
    rows, steps = [], 1000  # 1,000 seed steps before the first trial
    for i, (length, fell) in enumerate([(1000, False), (200, True), (1000, False), (50, True), (1000, False),
                                         (1000, False), (300, True)]):  # fmt: skip
        steps += length
        rows.append(episode(steps, 100.0 * (i + 1), length, fell))
    rows.append(episode(steps + 400, 9999.0, 400))  # the budget cut it: not complete
    assert gate.endpoint(rows, steps + 400, full_length=1000) == pytest.approx((300 + 400 + 500 + 600 + 700) / 5)
    assert gate.endpoint(rows, 1000 + 1000 + 200 + 1000 + 50 + 1000, full_length=1000) == pytest.approx(300.0)
    assert math.isnan(gate.endpoint(rows, 3000, full_length=1000))  # fewer than 5 complete episodes by then
    x, y = gate.curve(rows, full_length=1000)
    assert x.tolist() == [int(r["env_steps"]) for r in rows[4:7]] and y[-1] == pytest.approx(500.0)


def test_a_curve_is_the_endpoint_on_the_grid_up_to_the_budget_and_the_cli_commits_it(tmp_path):
    """The committed learning curve of a run directory: the endpoint every 1,000 env steps from 10,000 (NaN before
    five complete episodes), cut at the gate's budget; ``--out`` writes it beside the runs' rows."""
    import yaml

    from pets.experiments.curves import GRID_EVERY, GRID_FROM

    rows, steps = [], 1000
    for i in range(120):  # 120 complete 1,000-step episodes: 121k env steps, past the budget
        steps += 1000
        rows.append(episode(steps, float(i), 1000))
    points = gate.curve_rows({"env": "halfcheetah"}, rows, 1000)
    assert [p["env_steps"] for p in points] == list(range(GRID_FROM, gate.BUDGET + 1, GRID_EVERY))
    for p in points:
        assert p["reward"] == pytest.approx(gate.endpoint(rows, p["env_steps"], 1000)) and p["env"] == "halfcheetah"
    assert points[0]["reward"] == pytest.approx((4 + 5 + 6 + 7 + 8) / 5)  # episodes 0-8 ended by 10k steps
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.yaml").write_text(yaml.safe_dump({"env": "halfcheetah", "head": "delta", "seed": 3,
                                                         "max_env_steps": gate.BUDGET}))  # fmt: skip
    columns = ["trial", *rows[0], "plan_cpu_s", "cpu_time_s"]
    with (run_dir / "metrics.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, columns)
        writer.writeheader()
        writer.writerows({"trial": i, "plan_cpu_s": 1.0, "cpu_time_s": 2.0 * i} | r for i, r in enumerate(rows))
    assert gate.main([str(run_dir), "--out", str(tmp_path / "gate")]) == 0
    committed = list(csv.DictReader((tmp_path / "gate_curves.csv").open()))
    assert len(committed) == len(points) and committed[0]["seed"] == "3" and committed[0]["agent"] == "delta"
    assert float(committed[-1]["reward"]) == pytest.approx(points[-1]["reward"], rel=1e-5)


def run(seed: int, final: float, status: str = "complete") -> dict:
    steps = gate.BUDGET if status == "complete" else gate.BUDGET // 2
    return {"env": "halfcheetah", "agent": "delta", "seed": seed, "env_steps": steps, "reward_100k": final,
            "status": status}  # fmt: skip


def test_the_verdict_is_the_mean_over_seeds_against_the_threshold_with_a_run_without_endpoint_as_zero():
    (passed,) = gate.summary_rows([run(0, 3000.0), run(1, 2700.0), run(2, 2800.0)])
    assert passed["verdict"] == "passed" and passed["mean"] == pytest.approx(2833.33, abs=0.01)
    assert passed["ci_low"] <= passed["iqm"] <= passed["ci_high"]
    (failed,) = gate.summary_rows([run(0, 4000.0), run(1, 4000.0), run(2, math.nan)])  # 8,000 / 3 < 2,800
    assert failed["verdict"] == "not passed" and failed["mean"] == pytest.approx(8000 / 3)
    (partial,) = gate.summary_rows([run(0, 3000.0), run(1, math.nan, "partial")])
    assert partial["verdict"] == "partial" and math.isnan(partial["mean"])


def test_a_run_given_up_on_counts_as_zero_where_it_did_not_reach_and_the_verdict_is_read(tmp_path, capsys):
    """``--crashed RUN``: a run that stopped at 30k env steps (its training diverged) is ``crashed``, keeps its real
    25k endpoint and counts 0 at 50k and 100k; the verdict is read with it (registered: the worst outcome), where
    the same run given as a run leaves the env ``partial``."""
    import yaml

    def run_dir(name: str, seed: int, episodes: int, reward: float) -> Path:
        d = tmp_path / name
        d.mkdir()
        (d / "config.yaml").write_text(yaml.safe_dump({"env": "halfcheetah", "head": "delta", "seed": seed,
                                                       "max_env_steps": gate.BUDGET}))  # fmt: skip
        rows = [episode(1000 + 1000 * (i + 1), reward, 1000) for i in range(episodes)]
        with (d / "metrics.csv").open("w", newline="") as f:
            writer = csv.DictWriter(f, ["trial", *rows[0], "plan_cpu_s", "cpu_time_s"])
            writer.writeheader()
            writer.writerows({"trial": i, "plan_cpu_s": 1.0, "cpu_time_s": 9.0 * i} | r for i, r in enumerate(rows))
        return d

    done = [run_dir(f"s{seed}", seed, 99, 4000.0) for seed in (0, 1)]  # 100k env steps with the seed data
    stopped = run_dir("s2", 2, 29, 3500.0)
    assert gate.main([*map(str, done), "--crashed", str(stopped), "--out", str(tmp_path / "gate")]) == 0
    rows = list(csv.DictReader((tmp_path / "gate_runs.csv").open()))
    crashed = rows[-1]
    assert (crashed["seed"], crashed["status"], crashed["env_steps"]) == ("2", "crashed", "30000")
    assert float(crashed["reward_25k"]) == pytest.approx(3500.0) and crashed["reward_50k"] == crashed["reward_100k"]
    assert float(crashed["reward_100k"]) == 0.0
    (summary,) = gate.summary_rows(rows)
    assert summary["verdict"] == "not passed" and summary["mean"] == pytest.approx(8000 / 3)  # below 2,800
    assert gate.main([*map(str, done), str(stopped), "--out", str(tmp_path / "as-run")]) == 0
    (partial,) = gate.summary_rows(list(csv.DictReader((tmp_path / "as-run_runs.csv").open())))
    assert partial["verdict"] == "partial"
    capsys.readouterr()
    for args in ([str(stopped), "--crashed", str(stopped)], ["--pilots", "--crashed", str(stopped)]):
        with pytest.raises(SystemExit) as exit_info:
            gate.main([*args, "--out", str(tmp_path / "bad")])
        err = capsys.readouterr().err.strip().splitlines()
        assert exit_info.value.code == 2 and len(err) == 1 and "--crashed" in err[0], err


def test_an_input_that_is_not_what_its_option_takes_is_one_line_and_nothing_is_written(tmp_path, capsys):
    """Each was a traceback (or, for a random-policy data set given as SAC, rows labelled sac): an offline run, a
    truncated config.yaml, a file that is not pets.oracle's JSON, a data set for --peer; the gate's and the online
    study's commands read every input before writing, so nothing is written."""
    from pets.experiments.studies import locomotion
    from tests.processes import collect_random

    offline = tmp_path / "offline"  # as pets.train writes it: no episodes in metrics.csv
    offline.mkdir()
    (offline / "config.yaml").write_text("env: halfcheetah\nhead: delta\nseed: 0\n")
    (offline / "metrics.csv").write_text(
        "env_steps,episode_reward,episode_length,terminated,cpu_time_s\n100,nan,nan,nan,1\n"
    )
    truncated = tmp_path / "truncated"
    truncated.mkdir()
    (truncated / "config.yaml").write_text("env: [halfcheetah\nhead: {")
    (tmp_path / "o.json").write_text('{"a": 1}')
    random_data = collect_random(tmp_path / "random.npz", 1)
    cases = [
        ([str(offline)], "is not an online run (run_pets.py)"),
        ([str(truncated)], "config.yaml is not readable YAML"),
        (["--oracle", str(tmp_path / "o.json")], "is not a pets.oracle --json file"),
        (["--oracle", str(random_data)], "is not a pets.oracle --json file"),
        (["--peer", str(random_data)], "not a text CSV file"),
        (["--sac", str(random_data)], "is not a SAC collection (pets.collect --policy sac:STEPS); its policy: random"),
        (["--crashed", str(offline)], "is not an online run"),
    ]
    capsys.readouterr()
    for args, fragment in cases:
        with pytest.raises(SystemExit) as exit_info:
            gate.main([*args, "--out", str(tmp_path / "gate")])
        err = capsys.readouterr().err.strip().splitlines()
        assert exit_info.value.code == 2 and len(err) == 1 and fragment in err[0], (args, err)
    with pytest.raises(SystemExit) as exit_info:
        locomotion.main([str(offline), "--out", str(tmp_path / "study.csv")])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and len(err) == 1 and "is not an online run" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.json", "offline", "random.npz", "truncated"]


def test_oracle_files_become_rows_and_no_input_is_one_line_exit_2(tmp_path):
    import json
    import sys

    episodes = [{"steps": 139, "reward": 376.0, "terminated": True, "seconds": 1.0}]
    planner = {"name": "cem", "population": 100, "horizon": 15, "iterations": 3}
    (tmp_path / "hopper_cem.json").write_text(json.dumps({"planner": planner, "episodes": episodes}))
    (row,) = gate.oracle_rows(tmp_path / "hopper_cem.json")
    assert row["env"] == "hopper" and row["steps"] == 139 and row["fell"] == 1 and row["reward"] == 376.0
    assert row["termination_penalty"] == 0.0 and row["candidates"] == "open_loop"  # written before: the defaults
    assert gate.ceiling([row]) == {"hopper": 376.0}  # the locomotion preset's planner
    penalised = dict(planner, termination_penalty=100.0)
    (tmp_path / "hopper_pen.json").write_text(json.dumps({"planner": penalised, "episodes": episodes}))
    (row,) = gate.oracle_rows(tmp_path / "hopper_pen.json")
    assert row["termination_penalty"] == 100.0 and gate.ceiling([row]) == {}  # not the preset's setting
    closed = {"planner": dict(planner, candidates="feedback"), "episodes": episodes}
    (tmp_path / "hopper_feedback.json").write_text(json.dumps(closed))
    (row,) = gate.oracle_rows(tmp_path / "hopper_feedback.json")
    assert row["candidates"] == "feedback" and gate.ceiling([row]) == {}  # not the preset's candidates
    valued = {"planner": planner, "episodes": episodes, "value_from": "/runs/hopper-v2-s100"}
    (tmp_path / "hopper_value.json").write_text(json.dumps(valued))
    (row,) = gate.oracle_rows(tmp_path / "hopper_value.json")
    assert row["terminal_value"] == "hopper-v2-s100" and gate.ceiling([row]) == {}  # a learned value: no ceiling
    proc = warm.run([sys.executable, "-m", "pets.experiments.gate", "--out", str(tmp_path / "x")],
                    capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 2 and "give run directories" in proc.stderr and len(proc.stderr.splitlines()) == 1


def test_oracle_files_merge_into_the_committed_rows_of_other_files(tmp_path):
    """An oracle file run later (e.g. with a gate run's value) adds its rows; the committed rows of files not given
    (run on a machine since replaced) are kept, those of a file given again are replaced; --replace writes only
    the files given."""
    import json

    def oracle_file(name: str, rewards: list[float]) -> Path:
        episodes = [{"steps": 100, "reward": r, "terminated": True, "seconds": 1.0} for r in rewards]
        planner = {"name": "cem", "population": 100, "horizon": 15, "iterations": 3}
        (tmp_path / f"{name}.json").write_text(json.dumps({"planner": planner, "episodes": episodes}))
        return tmp_path / f"{name}.json"

    out = tmp_path / "locomotion"
    first, second = oracle_file("hopper_a", [1.0, 2.0]), oracle_file("hopper_b", [3.0])
    assert gate.main(["--oracle", str(first), str(second), "--out", str(out)]) == 0
    first.unlink()  # its machine replaced: only its committed rows remain
    second = oracle_file("hopper_b", [4.0, 5.0])  # the same file run again
    assert gate.main(["--oracle", str(second), "--out", str(out)]) == 0
    rows = list(csv.DictReader((tmp_path / "locomotion_oracle.csv").open()))
    assert [(r["source"], r["reward"]) for r in rows] == [("hopper_a", "1"), ("hopper_a", "2"), ("hopper_b", "4"),
                                                          ("hopper_b", "5")]  # fmt: skip
    assert gate.main(["--oracle", str(second), "--out", str(out), "--replace"]) == 0
    rows = list(csv.DictReader((tmp_path / "locomotion_oracle.csv").open()))
    assert [(r["source"], r["reward"]) for r in rows] == [("hopper_b", "4"), ("hopper_b", "5")]


def test_the_summary_and_the_docs_block_are_made_from_the_committed_runs_csv(tmp_path, monkeypatch):
    """pets.compare report's product: the verdict from locomotion_gate_runs.csv alone (the rule: the mean over the
    seeds against the threshold), and the block that shows both files."""
    from pets.experiments import published
    from pets.experiments.report import write_csv

    results = tmp_path / "docs" / "results"
    results.mkdir(parents=True)
    runs = [
        dict.fromkeys(gate.RUN_COLUMNS, "")
        | {"env": "halfcheetah", "agent": "delta", "seed": s, "env_steps": "100000", "reward_100k": r}
        for s, r in ((0, "3000"), (1, "2900"), (2, "2400"))
    ]
    write_csv(results / "locomotion_gate_runs.csv", [r | {"status": "complete"} for r in runs], gate.RUN_COLUMNS)
    curve = [{"env": "halfcheetah", "agent": "delta", "seed": s, "env_steps": n, "reward": n / 10 + s}
             for s in range(3) for n in (10_000, 11_000)]  # fmt: skip
    write_csv(results / "locomotion_gate_curves.csv", curve, gate.CURVE_COLUMNS)
    pilot = [{"run": "halfcheetah-v2-s100", "env": "halfcheetah", "env_steps": 10_000, "reward": 1.0}]
    write_csv(results / "locomotion_pilots_curves.csv", pilot, gate.PILOT_CURVE_COLUMNS)
    (tmp_path / "docs" / "figures").mkdir()
    monkeypatch.chdir(tmp_path)
    (product,) = [p for p in published.PRODUCTS if p.name.startswith("locomotion gate summary")]
    product.make()
    for name in ("locomotion_gate.png", "locomotion_pilots.png"):  # drawn from the committed curves alone
        assert (tmp_path / "docs" / "figures" / name).read_bytes().startswith(b"\x89PNG")
    (row,) = list(csv.DictReader((results / "locomotion_gate_summary.csv").open()))
    assert row["verdict"] == "not passed" and float(row["mean"]) == pytest.approx(8300 / 3, rel=1e-5)
    assert float(row["threshold"]) == 2800 and row["n_runs"] == "3"
    from pets.experiments.gate_published import gate_table

    text = gate_table(tmp_path)
    assert "| halfcheetah | delta | 2 |" in text and "not passed" in text


def test_the_ablation_block_names_each_arm_by_its_overrides_and_pairs_complete_seeds(tmp_path):
    """Each arm's endpoints, and against the full preset over the seeds both have complete: the mean
    difference, the pairs below it and the exact sign-flip p."""
    from pets.experiments.gate_published import ablation_table
    from pets.experiments.report import write_csv

    results = tmp_path / "docs" / "results"
    results.mkdir(parents=True)
    rows = [
        {"env": "halfcheetah", "seed": s, "overrides": o, "env_steps": n, "reward_100k": r}
        for s, o, n, r in (
            (100, "", 100000, 3000.0), (101, "", 100000, 2000.0), (100, "value.enabled=False", 100000, 1500.0),
            (101, "value.enabled=False", 100000, 1600.0), (102, "value.enabled=False", 40000, ""),
            (100, "planner.horizon=30", 100000, 9999.0),  # a pilot, not an arm
            (101, "model.iterations=0", 100000, 2500.0),
        )
    ]  # fmt: skip
    write_csv(results / "locomotion_pilots.csv", rows, list(rows[0]))
    lines = ablation_table(tmp_path).splitlines()
    assert lines[2] == "| full preset | 3000 | 2000 | not run | 2500 | - | - | - |"
    # -1500 and -400: of the 4 sign patterns, 2 have a mean as far from 0 (exact p 0.5); one pair: p 1
    assert lines[3] == "| without the value | 1500 | 1600 | partial (40k) | 1550 | -950 (2 pairs) | 2 of 2 | 0.5 |"
    assert lines[4] == "| epoch training | not run | 2500 | not run | 2500 | 500 (1 pair) | 0 of 1 | 1 |"
    assert len(lines) == 5


def test_committed_curves_keep_complete_runs_of_the_agents_asked_for(tmp_path):
    """The online study's SAC reference line: the gate's committed curves of complete SAC runs only."""
    from pets.experiments.gate_published import committed_curves
    from pets.experiments.report import write_csv

    runs = [dict.fromkeys(gate.RUN_COLUMNS, "") | {"env": "halfcheetah", "agent": a, "seed": s, "status": st}
            for a, s, st in (("sac", 0, "complete"), ("sac", 1, "partial"), ("delta", 0, "complete"))]  # fmt: skip
    write_csv(tmp_path / "locomotion_gate_runs.csv", runs, gate.RUN_COLUMNS)
    points = [{"env": "halfcheetah", "agent": a, "seed": s, "env_steps": n, "reward": float(n)}
              for a, s in (("sac", 0), ("sac", 1), ("delta", 0)) for n in (10_000, 11_000)]  # fmt: skip
    write_csv(tmp_path / "locomotion_gate_curves.csv", points, gate.CURVE_COLUMNS)
    assert committed_curves(tmp_path, agents={"sac"}) == {
        "halfcheetah": {"sac": {"0": [(10_000, 10_000.0), (11_000, 11_000.0)]}}
    }
    assert set(committed_curves(tmp_path)["halfcheetah"]) == {"sac", "delta"}
    assert committed_curves(tmp_path / "absent") == {}


def test_the_compute_block_sums_the_recorded_cpu_hours_per_part_and_env_counting_reused_runs_once(tmp_path):
    from pets.experiments.gate_published import compute_table
    from pets.experiments.report import write_csv

    results = tmp_path / "docs" / "results"
    results.mkdir(parents=True)
    gate_rows = [{"env": "halfcheetah", "agent": a, "seed": s, "cpu_hours": h}
                 for a, s, h in (("delta", 0, 1.5), ("delta", 1, 1.25), ("sac", 0, ""))]  # fmt: skip
    write_csv(results / "locomotion_gate_runs.csv", gate_rows, list(gate_rows[0]))
    cells = (("ant", 100, "planner.horizon=5", 0.75), ("ant", 100, "", 0.5), ("halfcheetah", 100, "", 0.25),
             ("halfcheetah", 101, "value.enabled=False", 1.0))  # fmt: skip
    pilots = [{"env": e, "seed": s, "overrides": o, "cpu_hours": h} for e, s, o, h in cells]
    write_csv(results / "locomotion_pilots.csv", pilots, list(pilots[0]))
    frozen = [{"run": r, "cpu_s": c} for r, c in (("ant-v7-78k-e300", 1800.0), ("ant-v5-s100", 1800.0))]
    write_csv(results / "locomotion_frozen_planning.csv", frozen, list(frozen[0]))
    online = [{"env": "halfcheetah", "model": m, "seed": s, "cpu_hours": h}
              for m, s, h in (("delta", 0, 1.5), ("gem", 0, 2.0), ("delta-groupfeat", 1, ""))]  # fmt: skip
    write_csv(results / "online_locomotion_runs.csv", online, list(online[0]))
    assert compute_table(tmp_path).splitlines()[2:] == [
        "| the gate's runs | halfcheetah | 2 | 2.75 |",
        "| the gate's pilots | ant | 2 | 1.25 |",
        "| the gate's ablation (with pilot v2) | halfcheetah | 2 | 1.25 |",
        "| frozen-model planning checks | ant | 2 | 1 |",
        "| the online study's runs | halfcheetah | 1 | 2 |",
        "| all of the above |  | 9 | 8.25 |",
    ]


def test_merging_keeps_committed_rows_in_their_order_and_replaces_every_row_of_a_key_given(tmp_path):
    from pets.experiments.report import merge_committed, write_csv

    path = tmp_path / "curves.csv"
    assert merge_committed(path, [{"seed": "0", "x": "1"}], ["seed"]) == ([{"seed": "0", "x": "1"}], 0)
    committed = [{"seed": s, "x": x} for s, x in (("0", "1"), ("1", "2"), ("1", "3"), ("2", "4"))]
    write_csv(path, committed, ["seed", "x"])
    new = [{"seed": "1", "x": "9"}, {"seed": "3", "x": "5"}]
    rows, kept = merge_committed(path, new, ["seed"])
    assert kept == 2 and [(r["seed"], r["x"]) for r in rows] == [("0", "1"), ("1", "9"), ("2", "4"), ("3", "5")]


def test_a_run_started_again_under_its_name_keeps_the_committed_rows_until_it_passes_them(tmp_path, capsys):
    """A run lost with its machine and started again from the start under its directory name: while its rows have
    fewer env steps than the committed ones (a curve: the largest), the committed rows stay and a line names the
    run; once the new rows reach further they replace them. Without ``progress`` the new rows replace as before."""
    from pets.experiments.report import merge_committed, write_csv

    path = tmp_path / "curves.csv"
    committed = [{"run": "a", "env_steps": n, "reward": r} for n, r in (("10000", "5"), ("26000", "9"))]
    committed.append({"run": "b", "env_steps": "20000", "reward": "1"})
    write_csv(path, committed, ["run", "env_steps", "reward"])
    rerun = [{"run": "a", "env_steps": "7000", "reward": "2"}, {"run": "b", "env_steps": "21000", "reward": "3"}]
    rows, _ = merge_committed(path, rerun, ["run"], progress="env_steps")
    assert [(r["run"], r["env_steps"]) for r in rows] == [("a", "10000"), ("a", "26000"), ("b", "21000")]
    assert "kept the committed rows of a (further in env_steps" in capsys.readouterr().err
    assert merge_committed(path, rerun, ["run"])[0] == rerun
    passed = [{"run": "a", "env_steps": n, "reward": "4"} for n in ("10000", "27000")]
    assert merge_committed(path, passed, ["run"], progress="env_steps")[0][:2] == passed


def test_the_gate_keeps_a_lost_pilot_row_while_its_rerun_is_behind(tmp_path):
    """The gate's pilot tables through its command line: a pilot started again under its directory name (12 trials
    so far) leaves the committed row and curve of the run that got to 26k env steps as they were; at 27k it
    replaces them."""
    from pets.config import config_yaml, make_config
    from pets.experiments.report import read_csv_rows, write_csv

    run_dir = tmp_path / "halfcheetah-v2-s100"
    run_dir.mkdir()
    (run_dir / "config.yaml").write_text(config_yaml(make_config("halfcheetah", "delta", "locomotion")))

    def trials(n: int) -> None:
        rows = [episode(1000 * (i + 2), float(i), 1000) for i in range(n)]
        with (run_dir / "metrics.csv").open("w", newline="") as f:
            writer = csv.DictWriter(f, ["trial", *rows[0], "plan_cpu_s", "cpu_time_s"])
            writer.writeheader()
            writer.writerows({"trial": i, "plan_cpu_s": 1.0, "cpu_time_s": 2.0 * i} | r for i, r in enumerate(rows))

    out, curves = tmp_path / "pilots", tmp_path / "pilots_curves.csv"
    trials(12)
    lost = dict(gate.pilot_row(run_dir), env_steps=26000, reward_last5=3222.45)
    write_rounded_csv(out.with_suffix(".csv"), [lost], list(lost))
    curve = [{"run": run_dir.name, "env": "halfcheetah", "env_steps": n, "reward": 1.0} for n in (10000, 26000)]
    write_csv(curves, curve, gate.PILOT_CURVE_COLUMNS)
    committed = read_csv_rows(out.with_suffix(".csv")), read_csv_rows(curves)
    assert gate.main([str(run_dir), "--pilots", "--out", str(out)]) == 0
    assert (read_csv_rows(out.with_suffix(".csv")), read_csv_rows(curves)) == committed
    trials(26)
    assert gate.main([str(run_dir), "--pilots", "--out", str(out)]) == 0
    assert read_csv_rows(out.with_suffix(".csv"))[0]["env_steps"] == "27000"
    assert read_csv_rows(curves)[-1]["env_steps"] == "27000"


def test_mbrl_lib_runs_become_gate_rows_complete_at_their_registered_budget_and_summarised_there(tmp_path):
    """A peer_mbrl.py learn CSV (one row per trial; its gem-pets rows ignored): each mbrl-lib run is a gate row,
    complete at the 50k env steps its 49 trials reach (the amendment of 21:45 UTC), its endpoint the gate's window
    there, and the summary reads the agent's endpoint at 50k, not the gate's 100k."""
    from pets.experiments import gate_references as ref
    from pets.experiments.report import write_csv

    rows = []
    for impl, seed in (("mbrl-lib", 0), ("mbrl-lib", 1), ("gem-pets", 0)):
        for t in range(49):
            rows.append({"env": "HalfCheetah-v5", "impl": impl, "seed": seed, "trial": t,
                         "episode_reward": 10.0 * t + seed, "episode_length": 1000, "env_steps": 1000 * (t + 2),
                         "run_cpu_s": 7200.0})  # fmt: skip
    path = tmp_path / "peer.csv"
    write_csv(path, rows, list(rows[0]))
    made = [gate.reference_row(r) for r in ref.peer_runs(path)]
    assert [(r["env"], r["agent"], r["seed"], r["status"]) for r in made] == [
        ("halfcheetah", "mbrl-lib", 0, "complete"),
        ("halfcheetah", "mbrl-lib", 1, "complete"),
    ]
    assert made[0]["env_steps"] == 50_000 and made[0]["cpu_hours"] == 2.0 and math.isnan(made[0]["reward_100k"])
    assert made[1]["reward_50k"] == pytest.approx(np.mean([10.0 * t + 1 for t in range(44, 49)]))
    (summary,) = gate.summary_rows(made)
    assert summary["endpoint_at"] == 50_000 and summary["mean"] == pytest.approx(
        np.mean([r["reward_50k"] for r in made])
    )
    assert gate.main(["--peer", str(path), "--out", str(tmp_path / "gate")]) == 0
    curves = list(csv.DictReader((tmp_path / "gate_curves.csv").open()))
    assert {c["agent"] for c in curves} == {"mbrl-lib"} and max(int(c["env_steps"]) for c in curves) == 50_000
    assert (
        gate.endpoint_budget([{"env_steps": 100_000, "status": "complete"}, {"env_steps": 50_000, "status": "partial"}])
        == gate.BUDGET
    )


def test_the_peer_block_sets_each_agent_beside_mbrl_lib_at_its_budget(tmp_path):
    """The mbrl-lib comparison: on the envs where mbrl-lib ran, each agent's complete runs at 50k env steps: the
    reward there (mean [min, max]), CPU-hours per 10k env steps over each run's own budget, and the reward per
    CPU-hour pro rata to 50k; partial runs and envs without mbrl-lib are left out, a missing CPU time is said."""
    from pets.experiments.gate_published import peer_table
    from pets.experiments.report import write_csv

    results = tmp_path / "docs" / "results"
    results.mkdir(parents=True)
    rows = [
        dict.fromkeys(gate.RUN_COLUMNS, "")
        | {"env": e, "agent": a, "seed": s, "env_steps": n, "reward_50k": r, "cpu_hours": c, "status": st}
        for e, a, s, n, r, c, st in (
            ("halfcheetah", "delta", 0, 100000, 2000.0, 1.0, "complete"),
            ("halfcheetah", "delta", 1, 100000, 3000.0, 2.0, "complete"),
            ("halfcheetah", "delta", 2, 60000, 9999.0, 0.5, "partial"),
            ("halfcheetah", "mbrl-lib", 0, 50000, 1000.0, 1.25, "complete"),
            ("halfcheetah", "sac", 0, 100000, 800.0, "", "complete"),
            ("ant", "delta", 0, 100000, 900.0, 0.8, "complete"),
        )
    ]  # fmt: skip
    write_csv(results / "locomotion_gate_runs.csv", rows, gate.RUN_COLUMNS)
    lines = peer_table(tmp_path).splitlines()
    # delta: 0.1 and 0.2 CPU-h per 10k steps; 2000 / 0.5 and 3000 / 1.0 reward per CPU-h to 50k
    assert lines[2] == "| halfcheetah | delta | 2 | 100000 | 2500 [2000, 3000] | 0.15 | 3500 |"
    assert lines[3] == "| halfcheetah | mbrl-lib | 1 | 50000 | 1000 [1000, 1000] | 0.25 | 800 |"
    assert lines[4] == "| halfcheetah | sac | 1 | 100000 | 800 [800, 800] | not recorded | not recorded |"
    assert len(lines) == 5


def test_the_cost_block_splits_each_runs_cpu_into_its_parts_and_projects_it_to_the_budget(tmp_path):
    """locomotion-cost: per run the shares of planning, model training, the value fit and the rest of its CPU over
    all its trials, and its CPU-hours pro rata to the gate's 100k env steps."""
    from pets.experiments.gate_published import cost_table
    from pets.experiments.report import write_csv

    results = tmp_path / "docs" / "results"
    results.mkdir(parents=True)
    rows = [
        {"run": "hc", "trial": t, "env_steps": n, "plan_cpu_s": p, "train_cpu_s": tr, "value_cpu_s": v, "cpu_s": c}
        for t, n, p, tr, v, c in ((0, 2000, 100.0, 50.0, 10.0, 200.0), (1, 3000, 200.0, 100.0, 10.0, 340.0))
    ]
    write_csv(results / "locomotion_cost_breakdown.csv", rows, list(rows[0]))
    lines = cost_table(tmp_path).splitlines()
    # 540 CPU-s over 3,000 env steps -> 5 CPU-h per 100k; 300 / 150 / 20 / 70 of 540
    assert lines[2] == "| hc | 3000 | 5 | 56 % | 28 % | 4 % | 13 % |" and len(lines) == 3
