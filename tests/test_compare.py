"""pets.compare (online and offline A/B runs) and pets.openloop end to end, on tiny configs.

The comparison commands run in-process through their CLI entry point ``main`` (argument parsing,
exit codes, files); the online runs themselves are real ``run_pets.py`` subprocesses. Ground truth:
the runs' own metrics.csv / eval.json, pets.experiments.statistics recomputed here, and the MuJoCo simulator for the
open-loop rewards.
"""

import csv
import json
import math

import numpy as np
import pytest

import envs
from pets import openloop, rundir
from pets.config import load_config, make_config
from pets.experiments import arguments, runner
from pets.experiments.cli import EXIT_FAILED, main
from pets.experiments.offline import compare_offline
from pets.experiments.report import fmt
from pets.experiments.statistics import bootstrap_ci, iqm
from tests.threads import one_thread
from tests.tiny import TINY_MODEL, TINY_PLANNER

TINY = [
    *TINY_PLANNER,
    *TINY_MODEL,
    "episode_length=30",
    "seed_steps=100",
]
TINY_OFFLINE = [
    "model.max_epochs=3",
    "model.hidden_size=32",
    "model.ensemble_size=2",
    "model.num_elites=2",
    "model.batch_size=32",
    "planner.population=16",
    "planner.particles=2",
    "planner.iterations=2",
]


def cli(capsys, *args):
    """``python -m pets.compare ARGS`` in this process: (exit code, stdout, stderr)."""
    try:
        code = main([str(a) for a in args])
    except SystemExit as err:
        code = err.code
    out = capsys.readouterr()
    return code, out.out, out.err


def csv_rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def snapshot(run_dir):
    return {name: (run_dir / name).stat().st_mtime_ns for name in ("config.yaml", "metrics.csv", "checkpoint.pt")}


# --------------------------------------------------------------------------- online
@pytest.fixture(scope="module")
def online(tmp_path_factory):
    """Three invocations: (1) delta seeds 0 and 9 for 1 trial, seed 9 a broken run; (2) delta and gem, seeds 0
    and 1, 2 trials (delta-s0 must be resumed); (3) the same again (everything reused)."""
    out = tmp_path_factory.mktemp("online")
    common = ["--envs", "invertedpendulum", "--out", out, "--workers", 2, "--preset", "fast", "--quiet", *TINY]
    # a broken run directory: valid config, corrupted checkpoint, no completed trial -> its resume fails
    broken = out / "runs" / "invertedpendulum-delta-s9"
    broken.mkdir(parents=True)
    overrides = dict(item.split("=") for item in TINY)
    rundir.write_config(
        broken, make_config("invertedpendulum", "delta", "fast", {**overrides, "seed": 9, "trials": 1, "threads": 1})
    )
    (broken / "checkpoint.pt").write_bytes(b"not a checkpoint")

    steps = {}
    for key, args in (
        ("first", ["--models", "delta", "--seeds", "0,9", "--trials", 1]),
        ("second", ["--models", "delta,gem", "--seeds", "0,1", "--trials", 2]),
        ("third", ["--models", "delta,gem", "--seeds", "0,1", "--trials", 2]),
    ):
        before = {
            d.name: (snapshot(d), csv_rows(d / "metrics.csv"))
            for d in (out / "runs").iterdir()
            if (d / "metrics.csv").exists()
        }
        try:
            code = main([str(a) for a in ["online", *args, *common]])
        except SystemExit as err:
            code = err.code
        steps[key] = {
            "code": code,
            "before": before,
            "summary": (out / "summary.csv").read_text(),
            "md": (out / "summary.md").read_text(),
        }
    return out, steps


def test_online_failed_run_is_reported_and_the_others_go_on(online):
    out, steps = online
    first = steps["first"]
    assert first["code"] == EXIT_FAILED
    rows = list(csv.DictReader(first["summary"].splitlines()))
    assert len(rows) == 1 and rows[0]["model"] == "delta" and rows[0]["n_seeds"] == "1"
    assert "invertedpendulum-delta-s9 (0/1 trials; failed: RuntimeError: exit 2" in first["md"]
    log = (out / "logs" / "invertedpendulum-delta-s9.log").read_text()
    assert "checkpoint.pt is not a readable checkpoint" in log and "Traceback" not in log  # one line (issue 17)


def test_online_incomplete_run_is_resumed_not_restarted(online):
    out, steps = online
    assert steps["second"]["code"] == 0
    run = out / "runs" / "invertedpendulum-delta-s0"
    snap, rows_after_first = steps["second"]["before"]["invertedpendulum-delta-s0"]
    assert len(rows_after_first) == 1
    # a restart would rewrite config.yaml and re-measure trial 0 (wall time); a resume appends trial 1
    assert (run / "config.yaml").stat().st_mtime_ns == snap["config.yaml"]
    rows = csv_rows(run / "metrics.csv")
    assert [r["trial"] for r in rows] == ["0", "1"] and rows[0] == rows_after_first[0]
    log = (out / "logs" / "invertedpendulum-delta-s0.log").read_text()
    assert log.count("run_pets.py --env") == 1 and log.count(f"run_pets.py --resume {run} --trials 2") == 1


def test_online_rerun_reuses_everything(online):
    out, steps = online
    assert steps["third"]["code"] == 0
    for name, (snap, rows) in steps["third"]["before"].items():
        if name.endswith("-s9"):
            continue
        assert snapshot(out / "runs" / name) == snap, name  # nothing was touched
        assert len(rows) == 2
    assert steps["third"]["summary"] == steps["second"]["summary"]
    assert sum(1 for _ in (out / "logs").iterdir()) == 5  # 4 runs + the broken one, no new logs


def test_online_summary_equals_statistics_recomputed_from_metrics(online):
    out, _ = online
    summary = {(r["env"], r["model"]): r for r in csv_rows(out / "summary.csv")}
    assert set(summary) == {("invertedpendulum", "delta"), ("invertedpendulum", "gem")}
    for model in ("delta", "gem"):
        finals, aucs = [], []
        for seed in (0, 1):
            rows = csv_rows(out / "runs" / f"invertedpendulum-{model}-s{seed}" / "metrics.csv")
            rewards = [float(r["episode_reward"]) for r in rows]
            assert len(rewards) == 2
            finals.append(np.mean(rewards[-2:]))  # --final-window 3, capped at the 2 trials
            aucs.append(np.mean(rewards))
        row = summary[("invertedpendulum", model)]
        assert int(row["n_seeds"]) == 2 and int(row["trials"]) == 2 and int(row["final_window"]) == 2
        assert float(row["final_mean"]) == pytest.approx(np.mean(finals), rel=1e-12)
        assert (float(row["final_ci_low"]), float(row["final_ci_high"])) == pytest.approx(bootstrap_ci(finals))
        assert float(row["final_iqm"]) == pytest.approx(iqm(finals))
        assert float(row["auc_mean"]) == pytest.approx(np.mean(aucs), rel=1e-12)
        assert (float(row["auc_ci_low"]), float(row["auc_ci_high"])) == pytest.approx(bootstrap_ci(aucs))
        assert min(finals) <= float(row["final_ci_low"]) <= float(row["final_ci_high"]) <= max(finals)
        walls = [
            float(csv_rows(out / "runs" / f"invertedpendulum-{model}-s{seed}" / "metrics.csv")[1]["wall_time_s"])
            for seed in (0, 1)
        ]
        assert float(row["wall_time_s_mean"]) == pytest.approx(np.mean(walls), rel=1e-12) and min(walls) > 0
        assert float(row["plan_seconds_per_step_mean"]) > 0 and row["planner"] == ""
    md = (out / "summary.md").read_text()
    assert "| delta | 2 |" in md and "| gem | 2 |" in md and "rewards_invertedpendulum.png" in md
    assert (out / "rewards_invertedpendulum.png").stat().st_size > 10_000
    assert (out / "walltime_invertedpendulum.png").stat().st_size > 10_000
    assert len(csv_rows(out / "summary_runs.csv")) == 4


def test_online_planners_axis_runs_every_model_planner_pair(tmp_path, capsys):
    code, printed, _ = cli(
        capsys,
        "online",
        "--envs",
        "invertedpendulum",
        "--models",
        "delta",
        "--planners",
        "cem,icem",
        "--seeds",
        3,
        "--trials",
        1,
        "--out",
        tmp_path,
        "--workers",
        2,
        "--preset",
        "fast",
        "--quiet",
        *TINY,
    )
    assert code == 0
    for planner in ("cem", "icem"):
        run = tmp_path / "runs" / f"invertedpendulum-delta-{planner}-s3"
        assert load_config(str(run / "config.yaml")).planner.name == planner
        assert len(csv_rows(run / "metrics.csv")) == 1
    summary = csv_rows(tmp_path / "summary.csv")
    assert [(r["model"], r["planner"], r["n_seeds"]) for r in summary] == [
        ("delta", "cem", "1"),
        ("delta", "icem", "1"),
    ]
    assert "| model | planner | seeds |" in printed and "| delta | icem | 1 |" in printed
    assert (tmp_path / "walltime_invertedpendulum.png").stat().st_size > 10_000


def test_openloop_on_an_online_run_replays_in_the_simulator(online, tmp_path, capsys):
    out, _ = online
    run = out / "runs" / "invertedpendulum-gem-s1"
    path = tmp_path / "ol.json"
    with one_thread():
        code = openloop.main(
            [
                "--run",
                str(run),
                "--steps",
                "6",
                "--episodes",
                "3",
                "--seed",
                "4",
                "--device",
                "cpu",
                "--json",
                str(path),
                "--quiet",
                "planner.population=12",
            ]
        )
    printed = capsys.readouterr().out
    assert code == 0 and "total reward" in printed and "open loop: invertedpendulum / gem / cem" in printed
    res = json.loads(path.read_text())
    assert res["planner_config"]["horizon"] == 6 and res["planner_config"]["population"] == 12
    assert res["planner_config"]["particles"] == 2  # the run's own setting
    check_open_loop_result(res, "invertedpendulum", steps=6, episodes=3)


# --------------------------------------------------------------------------- open loop (ground truth)
def check_open_loop_result(res, env, steps, episodes):
    """Structure of an open-loop result, and its rewards equal the simulator's for the planned actions."""
    assert {
        "run",
        "env",
        "model",
        "planner",
        "steps",
        "episodes",
        "seed",
        "reward_per_step",
        "total",
        "mean_reward_per_step",
        "rewards",
        "actions",
        "lengths",
        "terminated",
        "reset_seeds",
        "predicted_return",
        "planner_config",
    } <= set(res)
    assert res["env"] == env and res["steps"] == steps and res["episodes"] == episodes
    spec = envs.get(env)
    rewards, actions = np.array(res["rewards"]), np.array(res["actions"])
    assert rewards.shape == (episodes, steps) and actions.shape == (episodes, steps, spec.act_dim)
    assert (actions >= np.array(spec.action_low)).all() and (actions <= np.array(spec.action_high)).all()
    sim = spec.make()
    for i in range(episodes):
        sim.reset(seed=res["reset_seeds"][i])
        length = res["lengths"][i]
        for t in range(length):
            _, r, term, _, _ = sim.step(actions[i, t])
            assert rewards[i, t] == r
            assert term == (res["terminated"][i] and t == length - 1)
        assert (rewards[i, length:] == 0).all()  # nothing executed after a real termination
        assert length == steps or res["terminated"][i]
    sim.close()
    np.testing.assert_allclose(res["reward_per_step"]["mean"], rewards.mean(axis=0))
    assert len(res["reward_per_step"]["ci_low"]) == steps
    np.testing.assert_allclose(res["total"]["values"], rewards.sum(axis=1))
    assert res["total"]["mean"] == pytest.approx(rewards.sum(axis=1).mean())
    assert res["mean_reward_per_step"]["mean"] == pytest.approx(rewards.sum(axis=1).mean() / steps)
    assert len(res["predicted_return"]) == episodes and all(math.isfinite(v) for v in res["predicted_return"])


# --------------------------------------------------------------------------- offline
OFFLINE_ARGS = [
    "offline",
    "--envs",
    "invertedpendulum",
    "--models",
    "delta,gem",
    "--seeds",
    "0,1",
    "--episodes",
    8,
    "--test-episodes",
    4,
    "--horizons",
    "1,3,5",
    "--starts",
    20,
    "--openloop",
    "--planners",
    "cem,mppi",
    "--openloop-steps",
    12,
    "--openloop-episodes",
    2,
    "--preset",
    "fast",
    "--device",
    "cpu",
    "--quiet",
    *TINY_OFFLINE,
]


@pytest.fixture(scope="module")
def offline(tmp_path_factory):
    out = tmp_path_factory.mktemp("offline")
    result = compare_offline(
        ["invertedpendulum"],
        ["delta", "gem"],
        [0, 1],
        out,
        episodes=8,
        test_episodes=4,
        horizons=[1, 3, 5],
        starts=20,
        openloop=True,
        planners=["cem", "mppi"],
        openloop_steps=12,
        openloop_episodes=2,
        preset="fast",
        device="cpu",
        overrides=TINY_OFFLINE,
        progress=False,
    )
    return out, result


def test_offline_writes_data_runs_and_summaries(offline):
    out, result = offline
    assert result["failed"] == {} and result["data"] == {
        "invertedpendulum-train.npz": "collected",
        "invertedpendulum-test.npz": "collected",
    }
    assert all(done == ["train", "eval", "openloop_cem", "openloop_mppi"] for done in result["done"].values())
    for name in (
        "prediction.md",
        "prediction.csv",
        "prediction_runs.csv",
        "relative_error.png",
        "absolute_error_invertedpendulum.png",
        "openloop.md",
        "openloop.csv",
        "openloop_invertedpendulum.png",
    ):
        assert (out / name).is_file() and (out / name).stat().st_size > 100, name
    train, test = (np.load(out / "data" / f"invertedpendulum-{p}.npz") for p in ("train", "test"))
    assert int(train["seed"]) == 0 and int(test["seed"]) == 1 and len(train["lengths"]) == 8
    assert not np.array_equal(train["obs"][:4, 0], test["obs"][:, 0])  # separate data sets


def test_offline_prediction_csv_equals_the_runs_evaluations(offline):
    out, _ = offline
    rows = csv_rows(out / "prediction.csv")
    assert {(r["model"], r["horizon"]) for r in rows} == {(m, h) for m in ("delta", "gem") for h in ("1", "3", "5")}
    averaged = {}
    for r in rows:
        evals = [
            json.loads((out / "runs" / f"invertedpendulum-{r['model']}-s{s}" / "eval.json").read_text()) for s in (0, 1)
        ]
        assert all(e["model"] == r["model"] and e["env"] == "invertedpendulum" for e in evals)
        assert evals[0]["start_points"] == evals[1]["start_points"]  # paired: the same starts for every run
        assert all(e["standardized_by"] == str(out / "data" / "invertedpendulum-train.npz") for e in evals)
        values = [e["horizons"][r["horizon"]]["mean_step_error"] for e in evals]
        assert float(r["mean_step_error"]) == pytest.approx(np.mean(values), rel=1e-12)
        assert (float(r["ci_low"]), float(r["ci_high"])) == pytest.approx(bootstrap_ci(values))
        assert int(r["n_seeds"]) == 2
    for model in ("delta", "gem"):  # Fig. 2: per seed the mean over horizons, then the mean over seeds
        per_seed = []
        for s in (0, 1):
            e = json.loads((out / "runs" / f"invertedpendulum-{model}-s{s}" / "eval.json").read_text())
            per_seed.append(np.mean([e["horizons"][h]["mean_step_error"] for h in ("1", "3", "5")]))
        averaged[model] = np.mean(per_seed)
    top = max(averaged.values())
    lines = (out / "prediction.md").read_text().splitlines()
    line = next(row for row in lines if row.startswith("| invertedpendulum |"))
    delta, gem = (fmt(averaged[m] / top) for m in ("delta", "gem"))
    assert line == f"| invertedpendulum | {delta} | {gem} |"
    assert "1" in {fmt(v / top) for v in averaged.values()}


def test_offline_open_loop_results_replay_in_the_simulator(offline):
    out, _ = offline
    terminated = 0
    table = {(r["planner"], r["model"]): r for r in csv_rows(out / "openloop.csv")}
    assert set(table) == {(p, m) for p in ("cem", "mppi") for m in ("delta", "gem")}
    for planner in ("cem", "mppi"):
        for model in ("delta", "gem"):
            results = [
                json.loads((out / "runs" / f"invertedpendulum-{model}-s{s}" / f"openloop_{planner}.json").read_text())
                for s in (0, 1)
            ]
            for res in results:
                assert res["planner"] == planner and res["model"] == model
                check_open_loop_result(res, "invertedpendulum", steps=12, episodes=2)
                terminated += sum(res["terminated"])
            row = table[(planner, model)]
            assert float(row["reward_per_step_mean"]) == pytest.approx(
                np.mean([r["mean_reward_per_step"]["mean"] for r in results]), rel=1e-12
            )
    assert terminated > 0  # 12 open-loop steps of a barely trained model: the pendulum falls somewhere


def test_offline_rerun_reuses_and_new_horizons_only_re_evaluate(offline, capsys):
    out, _ = offline
    runs = sorted((out / "runs").iterdir())
    before = {d.name: {f.name: f.stat().st_mtime_ns for f in d.iterdir()} for d in runs}
    code, stdout, stderr = cli(capsys, *OFFLINE_ARGS, "--out", out)
    assert code == 0 and "4 runs: 4 reused, 0 with work to do" in stderr and "## invertedpendulum" in stdout
    assert {d.name: {f.name: f.stat().st_mtime_ns for f in d.iterdir()} for d in runs} == before
    args = [a if a != "1,3,5" else "1,2" for a in OFFLINE_ARGS]
    code, _, stderr = cli(capsys, *args, "--out", out)
    assert code == 0 and "4 reused" not in stderr
    for d in runs:  # evaluated again, not trained again, open loop untouched
        assert d.joinpath("checkpoint.pt").stat().st_mtime_ns == before[d.name]["checkpoint.pt"]
        assert d.joinpath("openloop_cem.json").stat().st_mtime_ns == before[d.name]["openloop_cem.json"]
        assert list(json.loads(d.joinpath("eval.json").read_text())["horizons"]) == ["1", "2"]
    assert {r["horizon"] for r in csv_rows(out / "prediction.csv")} == {"1", "2"}


def test_offline_refuses_other_data_or_config_in_the_same_directory(offline, capsys):
    out, _ = offline
    args = [a if a != 8 else 9 for a in OFFLINE_ARGS]  # --episodes 9
    code, _, err = cli(capsys, *args, "--out", out)
    assert code == 2 and "collected with other settings (episodes: 8 != 9)" in err
    code, _, err = cli(capsys, *OFFLINE_ARGS, "model.hidden_size=64", "--out", out)
    assert code == 2 and "model.hidden_size: 32 != 64" in err and len(err.strip().splitlines()) == 1


def test_offline_existing_policy_takes_the_data_files_as_they_are(offline, tmp_path, capsys):
    out, _ = offline
    result = compare_offline(
        ["invertedpendulum"],
        ["delta"],
        [0],
        out,
        episodes=1,
        test_episodes=1,
        policy="existing",
        horizons=[1, 2],
        starts=20,
        preset="fast",
        device="cpu",
        overrides=TINY_OFFLINE,
        progress=False,
    )
    assert result["data"] == {"invertedpendulum-train.npz": "reused", "invertedpendulum-test.npz": "reused"}
    assert result["failed"] == {} and all("train" not in todo for todo in result["todo"].values())
    code, _, err = cli(
        capsys, "offline", "--envs", "reacher", "--models", "delta", "--policy", "existing", "--out", tmp_path
    )
    assert code == 2 and "--policy existing needs the data file" in err


def test_online_refuses_an_offline_run_directory(offline, capsys):
    out, _ = offline  # same config as the offline runs (trials aside): only the run kind differs
    code, _, err = cli(
        capsys,
        "online",
        "--envs",
        "invertedpendulum",
        "--models",
        "delta",
        "--seeds",
        0,
        "--trials",
        1,
        "--out",
        out,
        "--preset",
        "fast",
        "--device",
        "cpu",
        *TINY_OFFLINE,
        "model.patience=20",
    )
    assert code == 2 and "is an offline training run" in err


# --------------------------------------------------------------------------- pool and usage errors
def test_process_pool_reports_a_failed_job_and_finishes_the_others():
    jobs = [
        ("good", arguments.split_list, ("a,b", "x")),
        ("bad", arguments.split_list, ("a,,b", "x")),
        ("also good", arguments.parse_seeds, ("3,1",)),
    ]
    results = runner.run_pool(jobs, 2, processes=True, progress=False, desc="test")
    assert results["good"] == (True, ["a", "b"]) and results["also good"] == (True, [3, 1])
    assert results["bad"][0] is False and "UsageError" in results["bad"][1] and "empty items" in results["bad"][1]


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["online", "--envs", "pong", "--models", "delta", "--trials", 1], "unknown env 'pong'"),
        (["online", "--envs", "reacher", "--models", "delta,transformer", "--trials", 1], "accepted: delta, gem"),
        (["online", "--envs", "reacher", "--models", "delta", "--seeds", "0,x", "--trials", 1], "--seeds"),
        (["online", "--envs", "reacher,", "--models", "delta", "--trials", 1], "without empty items"),
        (["online", "--envs", "reacher", "--models", "delta", "--trials", 0], "must be >= 1"),
        (
            ["online", "--envs", "reacher", "--models", "delta", "--trials", 1, "planner.popsize=3"],
            "planner.population",
        ),
        (["online", "--envs", "reacher", "--models", "delta", "--trials", 1, "seed=3"], "--seeds"),
        (["online", "--envs", "reacher", "--models", "delta", "--trials", 1, "--planners", "cem,ddp"], "accepted: cem"),
        (
            [
                "online",
                "--envs",
                "reacher",
                "--models",
                "delta",
                "--trials",
                1,
                "--planners",
                "cem",
                "planner.name=mppi",
            ],
            "--planners or planner.name=",
        ),
        (["offline", "--envs", "reacher", "--models", "delta", "--horizons", "1,a"], "comma-separated"),
        (["offline", "--envs", "reacher", "--models", "delta", "--planners", "cem,ddp"], "accepted: cem"),
        (
            ["offline", "--envs", "reacher", "--models", "delta", "--policy", "run:x"],
            "smooth-random[:BETA], sac[:STEPS] or existing",
        ),
        (["online", "--envs", "reacher", "--models", "delta"], "--trials"),
        (["sweep", "--envs", "reacher"], "invalid choice"),
    ],
)
def test_bad_input_exits_2_with_one_line(args, fragment, capsys, tmp_path):
    code, _, err = cli(capsys, *args, "--out", tmp_path / "never")
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, err
    assert "error:" in lines[0] and fragment in lines[0]
    assert not (tmp_path / "never").exists()


def test_models_come_from_config_heads_at_run_time(monkeypatch):
    from pets import config

    monkeypatch.setattr(config, "HEADS", ("delta", "gem", "novel"))
    assert arguments.parse_models("novel,delta") == ["novel", "delta"]


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--planner", "ddp"], "unknown planner 'ddp'"),
        (["model.lr=0.1"], "must be planner keys"),
        (["planner.horizon=3"], "--steps"),
        (["planner.population=abc"], "planner.population"),
        (["--steps", "0"], "--steps must be >= 1"),
    ],
)
def test_openloop_bad_input_exits_2(args, fragment, offline, capsys):
    out, _ = offline
    with pytest.raises(SystemExit) as err:
        openloop.main(["--run", str(out / "runs" / "invertedpendulum-delta-s0"), *args])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert err.value.code == 2 and len(lines) == 1 and fragment in lines[0]
