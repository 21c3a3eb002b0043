"""The offline commands end to end: pets.collect -> pets.train -> pets.evaluate, on tiny real MuJoCo data.

Ground truth comes from the simulator (reset observations, rewards); the error metrics themselves are
tested in tests/test_metrics.py. Subprocesses run with one torch thread: tiny models on a shared 2-core
machine are many times slower with two.
"""

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import envs
from dynamics.model import DynamicsModel
from pets import builder
from pets.data.collect import collect, episode_seeds, make_policy
from pets.data.datasets import load_dataset, save_dataset, transitions
from pets.learning.evaluation import HORIZON_KEYS, evaluate, sample_starts
from pets.learning.offline import OFFLINE_DEFAULTS, offline_config
from pets.models import make_model
from pets.planning.propagation import TrajectoryEvaluator
from pets.runs import rundir
from tests import warm
from tests.threads import one_thread
from tests.tiny import TINY_MODEL as RUN_MODEL
from tests.tiny import TINY_PLANNER

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
TINY_MODEL = ["model.hidden_size=32", "model.ensemble_size=2", "model.num_elites=2", "model.batch_size=32"]
TINY_RUN = [
    "--preset",
    "fast",
    *TINY_PLANNER,
    *RUN_MODEL,
    "episode_length=15",
    "seed_steps=60",
    "--quiet",
]


def command(module, *args):
    target = ["-m", module] if not module.endswith(".py") else [str(ROOT / module)]
    return [sys.executable, *target, *map(str, args)]


def run(module, *args, check=True, timeout=300):
    proc = warm.run(command(module, *args), cwd=ROOT, capture_output=True, text=True, timeout=timeout, env=ENV)
    if check and proc.returncode != 0:
        raise AssertionError(f"{module} exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


def run_parallel(jobs, timeout=300):
    """Run independent commands at once (one torch thread each); {name: stdout}, all must succeed."""
    procs = {
        name: subprocess.Popen(
            command(*job), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV
        )
        for name, job in jobs.items()
    }
    out = {}
    for name, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=timeout)
        assert proc.returncode == 0, f"{name}: exit {proc.returncode}\n{stdout}\n{stderr}"
        out[name] = stdout
    return out


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """Every command of the offline pipeline, run once for the whole module (independent ones in parallel)."""
    w = tmp_path_factory.mktemp("offline")
    run_parallel(
        {
            "ip": ("pets.collect", *"--env InvertedPendulum-v5 --policy random --episodes 6 --seed 1".split(), "--out")
            + (w / "ip.npz", "--quiet"),
            "reacher": ("pets.collect", *"--env reacher --policy smooth-random --episodes 12 --seed 2".split())
            + ("--out", w / "reacher.npz", "--quiet"),
            "online": ("run_pets.py", *"--env invertedpendulum --trials 1 --seed 0".split(), "--out", w / "online")
            + tuple(TINY_RUN),
        }
    )
    reacher = ("pets.train", "--data", w / "reacher.npz")
    jobs = {
        "delta": (*reacher, "--model", "delta", "--out", w / "delta", *"--epochs 60 --seed 0 --device cpu".split())
        + ("--quiet", *(a for a in TINY_MODEL if not a.startswith("model.hidden_size=")), "model.hidden_size=64"),
        "gem": (*reacher, "--model", "gem", "--out", w / "gem", "--epochs", "3", "--quiet", *TINY_MODEL),
        "agent": ("pets.collect", "--policy", f"run:{w / 'online'}", *"--episodes 2 --max-steps 8 --seed 4".split())
        + ("--device", "cpu", "--out", w / "agent.npz", "--quiet"),
    }
    w.joinpath("agent.stdout").write_text(run_parallel(jobs)["agent"])
    return w


@pytest.fixture(scope="module")
def ip_data(work):
    return work / "ip.npz"


@pytest.fixture(scope="module")
def reacher_data(work):
    return work / "reacher.npz"


@pytest.fixture(scope="module")
def delta_run(work):
    return work / "delta"


@pytest.fixture(scope="module")
def online_run(work):
    return work / "online"


# --------------------------------------------------------------------------- collect
@pytest.mark.parametrize("name", ["ip", "reacher"])
def test_collect_file_format_and_simulator_ground_truth(name, ip_data, reacher_data):
    path, env, n = (ip_data, "invertedpendulum", 6) if name == "ip" else (reacher_data, "reacher", 12)
    data = load_dataset(path)
    spec = envs.get(env)
    obs, act, rew, term, lengths = (data[k] for k in ("obs", "act", "rew", "terminated", "lengths"))
    t = act.shape[1]
    assert str(data["env"]) == env and data["env"].shape == ()
    assert obs.shape == (n, t + 1, spec.obs_dim) and act.shape == (n, t, spec.act_dim) and rew.shape == (n, t)
    assert obs.dtype == act.dtype == rew.dtype == np.float64 and term.dtype == np.bool_
    assert lengths.dtype == np.int64 and lengths.max() == t and lengths.min() >= 1
    real = np.arange(t)[None] < lengths[:, None]
    assert np.isfinite(act[real]).all() and np.isnan(act[~real]).all() and np.isnan(rew[~real]).all()
    for i, k in enumerate(lengths):
        assert np.isfinite(obs[i, : k + 1]).all() and np.isnan(obs[i, k + 1 :]).all()
        # an episode ends by termination exactly when it is shorter than the time limit
        assert term[i, : k - 1].sum() == 0 and bool(term[i, k - 1]) == (k < spec.episode_length)
    if env == "reacher":
        assert (lengths == 50).all() and not term.any()
    else:
        assert term.any()
    assert (act[real] >= np.array(spec.action_low)).all() and (act[real] <= np.array(spec.action_high)).all()

    # the reset observation of the real simulator with the stored (and documented) reset seeds
    sim = spec.make()
    for i in range(n):
        assert int(data["reset_seeds"][i]) == episode_seeds(int(data["seed"]), i)[0]
        np.testing.assert_array_equal(obs[i, 0], sim.reset(seed=int(data["reset_seeds"][i]))[0])
    # replaying the stored actions in the simulator gives the stored next observations and rewards
    sim.reset(seed=int(data["reset_seeds"][0]))
    for s in range(lengths[0]):
        o, r, *_ = sim.step(act[0, s])
        np.testing.assert_array_equal(o, obs[0, s + 1])
        assert r == rew[0, s]
    sim.close()
    # the catalogue's exact reward and termination functions agree with the stored transitions
    o, a, o2 = (torch.as_tensor(x) for x in transitions(data))
    np.testing.assert_allclose(spec.reward(o, a, o2).numpy(), rew[real], rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(spec.terminated(o, a, o2).numpy(), term[real])


def test_collect_same_seed_same_bytes_and_episode_prefix(work, ip_data):
    # an independent second collection with the same arguments (in this process) writes the same bytes
    again = save_dataset(work / "ip_again.npz", collect(envs.get("invertedpendulum"), "random", 6, seed=1))
    assert ip_data.read_bytes() == again.read_bytes()
    other = collect(envs.get("invertedpendulum"), "random", 3, seed=2)
    assert not np.array_equal(other["obs"][:, 0], load_dataset(ip_data)["obs"][:3, 0])
    # the first k episodes do not depend on --episodes (and the function equals the command)
    data, first = load_dataset(ip_data), collect(envs.get("invertedpendulum"), "random", 3, seed=1)
    np.testing.assert_array_equal(first["lengths"], data["lengths"][:3])
    t = first["act"].shape[1]
    np.testing.assert_array_equal(first["obs"], data["obs"][:3, : t + 1])
    np.testing.assert_array_equal(first["act"], data["act"][:3, :t])


def test_smooth_random_is_smoother_than_random_and_still_spans_the_bounds(reacher_data):
    spec = envs.get("reacher")
    span = np.array(spec.action_high) - np.array(spec.action_low)
    smooth = load_dataset(reacher_data)["act"]
    rough = collect(spec, "random", 4, seed=2)["act"]

    def jump(a):
        return float(np.nanmean(np.abs(np.diff(a, axis=1)) / span))

    assert jump(rough) == pytest.approx(1 / 3, abs=0.05)  # E|U - U'| = 1/3 for i.i.d. uniforms
    assert jump(smooth) < 0.5 * jump(rough)
    flat = smooth.reshape(-1, spec.act_dim)
    # marginals stay uniform over the bounds: both halves of every dimension are visited
    assert ((flat < 0).mean(0) > 0.2).all() and ((flat > 0).mean(0) > 0.2).all()


def test_collect_with_the_mpc_agent_of_a_run(work, online_run):
    data = load_dataset(work / "agent.npz")
    assert str(data["env"]) == "invertedpendulum" and str(data["policy"]) == f"run:{online_run}"
    assert data["lengths"].max() <= 8 and data["act"].shape[0] == 2
    assert "2 episodes" in (work / "agent.stdout").read_text()
    # a run of another env is refused
    with pytest.raises(ValueError, match="trained on invertedpendulum"):
        make_policy(f"run:{online_run}", envs.get("reacher"))


# --------------------------------------------------------------------------- train
def test_train_writes_a_run_directory_that_load_model_reads(delta_run, reacher_data):
    cfg, spec, model = builder.load_model(delta_run)
    head, ensemble = model.head, model.network
    assert cfg.env == "reacher" and cfg.head == "delta" and head.name == "delta"
    assert cfg.model.max_epochs == 60 and cfg.model.hidden_size == 64 and cfg.model.patience == 20
    assert ensemble.ensemble_size == 2 and ensemble.elites.numel() == 2
    state = rundir.load_checkpoint(delta_run)
    assert state["trials_done"] == 0 and "optimizer" in state["trainer"] and len(state["rows"]) == 1
    assert state["offline"]["transitions"] == int(load_dataset(reacher_data)["lengths"].sum()) == 600
    (row,) = rundir.read_metrics(delta_run / rundir.METRICS_FILE)
    assert row["env_steps"] == 600 and 1 <= row["model_epochs"] <= 60
    assert math.isfinite(row["model_train_loss"]) and math.isfinite(row["model_val_loss"])
    assert math.isnan(row["trial"]) and math.isnan(row["episode_reward"])
    # the normaliser was fitted on the real transitions only (padding would make it NaN)
    assert torch.isfinite(ensemble.input_mean).all() and (ensemble.input_std > 0).all()


def test_train_gem_head(work, reacher_data):
    out = work / "gem"
    cfg, spec, model = builder.load_model(out)
    head, ensemble = model.head, model.network
    assert cfg.head == "gem" and type(head).__name__ == "GemHead" and ensemble.out_dim == head.target_dim
    with one_thread():
        res = evaluate(out, reacher_data, [1, 5], starts=20, seed=0, mode="mean", device="cpu")
    assert all(math.isfinite(v["mean_step_error"]) for v in res["horizons"].values())


def test_offline_defaults_and_epochs_precedence():
    cfg = offline_config("reacher", "delta")
    assert cfg.model.max_epochs == OFFLINE_DEFAULTS["model.max_epochs"] == 300
    assert cfg.model.patience == OFFLINE_DEFAULTS["model.patience"] == 20
    assert offline_config("reacher", "delta", {"model.max_epochs": "7"}).model.max_epochs == 7
    assert offline_config("reacher", "delta", {"model.max_epochs": "7"}, epochs=9).model.max_epochs == 9


# --------------------------------------------------------------------------- evaluate
def test_evaluate_cli_json(work, delta_run, reacher_data):
    out = work / "eval.json"
    proc = run(
        "pets.evaluate",
        "--run",
        delta_run,
        "--data",
        reacher_data,
        "--starts",
        50,
        "--seed",
        3,
        "--device",
        "cpu",
        "--json",
        out,
        "--train-data",
        reacher_data,
    )
    res = json.loads(out.read_text())
    assert {"run", "data", "env", "model", "horizons"} <= set(res)
    assert res["env"] == "reacher" and res["model"] == "delta" and res["mode"] == "mean"
    assert res["standardized_by"] == str(reacher_data)
    assert list(res["horizons"]) == ["1", "5", "10", "25", "50"]
    assert res["starts"] == 12  # horizon 50 in 50-step episodes: only t = 0 of each of the 12 episodes
    for row in res["horizons"].values():
        assert tuple(row) == HORIZON_KEYS
        assert all(math.isfinite(v) and v >= 0 for v in row.values())
        parts = ("translation_error", "velocity_error", "other_error", "derived_error")
        assert row["mean_step_error"] >= max(row[p] for p in parts) - 1e-12
        assert row["derived_error"] == 0 and row["nonfinite_fraction"] == 0  # reacher: no derived entries
        assert 0 < row["rotation_error"] <= math.pi * math.sqrt(2) and 0 < row["standardized_error"]
    one = res["horizons"]["1"]
    assert one["mean_step_error"] == pytest.approx(one["final_step_error"])
    assert "mean_step_error" in proc.stdout and "standardized_error" in proc.stdout and "\n     50 " in proc.stdout


def test_evaluate_standardizes_by_the_training_data(delta_run, reacher_data, ip_data):
    data = load_dataset(reacher_data)
    train = {k: v[:6] if k not in ("env", "policy", "seed") else v for k, v in data.items()}
    with one_thread():
        own = evaluate(delta_run, reacher_data, [1, 5], starts=30, seed=0, device="cpu")
        by_train = evaluate(delta_run, reacher_data, [1, 5], starts=30, seed=0, device="cpu", train_data=train)
        with pytest.raises(ValueError, match="training data set is from invertedpendulum"):
            evaluate(delta_run, reacher_data, [1], starts=30, device="cpu", train_data=ip_data)
    assert own["standardized_by"] == "test data" and by_train["standardized_by"] == "arrays"
    for h in ("1", "5"):
        a, b = own["horizons"][h], by_train["horizons"][h]
        assert {k: v for k, v in a.items() if k != "standardized_error"} == {
            k: v for k, v in b.items() if k != "standardized_error"
        }
        assert a["standardized_error"] != b["standardized_error"]


def test_trained_model_beats_untrained_one_step(work, delta_run, reacher_data):
    untrained = work / "untrained"
    shutil.copytree(delta_run, untrained)
    cfg, spec, trained = builder.load_model(delta_run)
    torch.manual_seed(7)
    fresh = make_model(cfg, spec, torch.device("cpu"))
    for name in ("input_mean", "input_std", "target_mean", "target_std"):  # same normalisers: only training differs
        getattr(fresh.network, name).copy_(getattr(trained.network, name))
    state = rundir.load_checkpoint(untrained)
    state["model"] = fresh.state_dict()
    rundir.save_checkpoint(untrained, state)
    with one_thread():
        good = evaluate(delta_run, reacher_data, [1], starts=300, seed=0, device="cpu")["horizons"]["1"]
        bad = evaluate(untrained, reacher_data, [1], starts=300, seed=0, device="cpu")["horizons"]["1"]
    assert good["mean_step_error"] < 0.9 * bad["mean_step_error"]


def test_evaluate_sample_mode_and_an_online_run_with_skipped_horizons(online_run, ip_data, delta_run, reacher_data):
    messages = []
    with one_thread():
        res = evaluate(
            online_run, ip_data, [1, 2, 3, 1000], starts=10, seed=0, mode="sample", device="cpu", log=messages.append
        )
        a = evaluate(delta_run, reacher_data, [1, 10], starts=40, seed=5, mode="sample", device="cpu")
        b = evaluate(delta_run, reacher_data, [1, 10], starts=40, seed=5, mode="sample", device="cpu")
        m = evaluate(delta_run, reacher_data, [1, 10], starts=40, seed=5, mode="mean", device="cpu")
    assert res["skipped_horizons"] == [1000] and any("1000" in msg for msg in messages)
    assert list(res["horizons"]) == ["1", "2", "3"] and res["model"] == "delta"
    assert all(math.isfinite(v) and v >= 0 for row in res["horizons"].values() for v in row.values())
    assert a == b and a["start_points"] == m["start_points"]  # seeded; same starts for both modes
    assert a["horizons"]["10"]["mean_step_error"] != m["horizons"]["10"]["mean_step_error"]


def test_mean_rollout_matches_the_planners_expectation_propagation(delta_run, reacher_data):
    cfg, spec, model = builder.load_model(delta_run)
    head, ensemble = model.head, model.network
    data = load_dataset(reacher_data)
    obs0 = torch.as_tensor(data["obs"][:3, 5], dtype=torch.float32)
    acts = torch.as_tensor(data["act"][:3, 5:25], dtype=torch.float32)
    with one_thread():
        ours = DynamicsModel(head, ensemble).rollout(obs0, acts, "mean")
        for i in range(3):
            evaluator = TrajectoryEvaluator(
                DynamicsModel(head, ensemble), spec.reward, None, particles=1, propagation="expectation"
            )
            theirs, _ = evaluator.rollout(obs0[i], acts[i : i + 1])
            torch.testing.assert_close(ours[i], theirs[0, 0, 1:], rtol=1e-5, atol=1e-5)


def test_sample_starts_leave_room_and_are_distinct():
    lengths = np.array([3, 10, 1, 7])
    pairs = sample_starts(lengths, 4, 100, np.random.default_rng(0))
    assert len(pairs) == (10 - 3) + (7 - 3) and (pairs[:, 1] + 4 <= lengths[pairs[:, 0]]).all()
    few = sample_starts(lengths, 4, 5, np.random.default_rng(0))
    assert len(few) == 5 and len({tuple(p) for p in few}) == 5 and (few[:, 1] + 4 <= lengths[few[:, 0]]).all()


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "module, args, fragment",
    [
        ("pets.collect", ["--env", "pong", "--policy", "random", "--out", "x.npz"], "invertedpendulum"),
        ("pets.collect", ["--env", "reacher", "--policy", "greedy", "--out", "x.npz"], "smooth-random"),
        ("pets.collect", ["--env", "reacher", "--policy", "run:/nonexistent/run", "--out", "x.npz"], "does not exist"),
        ("pets.collect", ["--env", "reacher", "--policy", "smooth-random:1.5", "--out", "x.npz"], "[0, 1)"),
        ("pets.collect", ["--policy", "random", "--out", "x.npz"], "--env is required"),
        ("pets.collect", ["--env", "reacher", "--policy", "random", "--out", "config.yaml"], "must name an .npz file"),
        ("pets.collect", ["--env", "reacher", "--policy", "random", "--out", "kept.npz"], "never writes over a file"),
        ("pets.train", ["--data", "/nonexistent.npz", "--model", "delta", "--out", "r"], "does not exist"),
        ("pets.train", ["--data", "/nonexistent.npz", "--model", "mlp", "--out", "r"], "delta, gem"),
        # a directory given as the data set was said not to exist
        ("pets.train", ["--data", "killed", "--model", "delta", "--out", "r"], "killed is a directory; give a data"),
        ("pets.evaluate", ["--run", "/nonexistent/run", "--data", "x.npz"], "not a run directory"),
        # a run killed (kill -9) before it wrote its config leaves only its lock: every tool names it so
        ("pets.evaluate", ["--run", "killed", "--data", "x.npz"], "killed holds no run"),
        ("pets.openloop", ["--run", "killed"], "killed holds no run"),
        ("pets.visualize", ["--runs", "killed", "--data", "x.npz", "--out", "x.png"], "killed holds no run"),
        ("pets.oracle", ["--env", "invertedpendulum", "--value-from", "killed"], "--value-from killed holds no run"),
        ("pets.evaluate", ["--run", "r", "--data", "x.npz", "--horizons", "1,a"], "comma-separated"),
        ("pets.evaluate", ["--run", "r", "--data", "x.npz", "--mode", "median"], "mean"),
    ],
)
def test_bad_input_exits_2_with_one_line(module, args, fragment, tmp_path):
    (tmp_path / "kept.npz").write_bytes(b"someone's data set")  # was written over without a word
    (tmp_path / "killed").mkdir()
    (tmp_path / "killed" / ".lock").write_text("12345\n")
    proc = warm.run(
        [sys.executable, "-m", module, *args],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        env={**ENV, "PYTHONPATH": str(ROOT)},
    )
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"{module}: error: ") and fragment in lines[0]
    assert (tmp_path / "kept.npz").read_bytes() == b"someone's data set"


def test_a_directory_given_as_a_data_set_is_named_as_a_directory(tmp_path):
    """load_dataset (pets.train, pets.visualize, the API) said a directory given as the data set did not exist."""
    from pets.data.datasets import load_dataset

    with pytest.raises(ValueError, match=r"^data file .* is a directory; give a data set file \(\.npz\)$"):
        load_dataset(tmp_path)
    with pytest.raises(ValueError, match=r"^data file .*none\.npz does not exist$"):
        load_dataset(tmp_path / "none.npz")


def test_bad_data_and_mismatched_env_exit_2(work, delta_run, ip_data, reacher_data):
    broken = work / "broken.npz"
    broken.write_bytes(b"not a zip file")
    cases = [
        ("pets.train", ["--data", broken, "--model", "delta", "--out", work / "never"], "is not an .npz archive"),
        (
            "pets.train",
            ["--data", ip_data, "--model", "delta", "--out", work / "never", "model.sizes=3"],
            "unknown config key",
        ),
        ("pets.evaluate", ["--run", delta_run, "--data", ip_data], "invertedpendulum"),
        ("pets.evaluate", ["--run", delta_run, "--data", work], "is a directory; give a data set file (.npz)"),
        (
            "pets.evaluate",
            ["--run", delta_run, "--data", reacher_data, "--train-data", work / "missing.npz"],
            "train data file",
        ),
        (
            "pets.evaluate",
            ["--run", delta_run, "--data", reacher_data, "--train-data", ip_data],
            "training data set is from invertedpendulum",
        ),
    ]
    for module, args, fragment in cases:
        proc = run(module, *args, check=False, timeout=120)
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        assert proc.returncode == 2 and len(lines) == 1 and fragment in lines[0], proc.stderr
    assert not (work / "never").exists()


# --------------------------------------------------------------------------- closed loop with a frozen model
def test_closed_loop_mpc_with_the_frozen_model_replays_in_the_simulator(delta_run, tmp_path):
    """Issue 38: MPC with a pre-trained model; the recorded rewards are the simulator's for the executed actions,
    the same seed gives the same episodes, and the run's checkpoint is not touched."""
    import hashlib

    from pets.planning.openloop import closed_loop

    small = {"planner.population": 20, "planner.iterations": 1, "planner.particles": 2, "planner.horizon": 5}
    ckpt = delta_run / "checkpoint.pt"
    before = hashlib.sha256(ckpt.read_bytes()).hexdigest()
    res = closed_loop(delta_run, "cem", steps=12, episodes=2, seed=3, overrides=small, device="cpu")
    assert res["mode"] == "closed" and res["planner_config"]["horizon"] == 5 and res["planner_config"]["name"] == "cem"
    spec = envs.get("reacher")
    sim = spec.make()
    for i in range(2):
        sim.reset(seed=res["reset_seeds"][i])
        for t in range(res["lengths"][i]):
            _, reward, terminated, _, _ = sim.step(np.array(res["executed_actions"][i][t]))
            assert reward == pytest.approx(res["rewards"][i][t], rel=1e-12, abs=1e-12)
    assert res["total"]["values"] == pytest.approx(np.sum(res["rewards"], axis=1).tolist(), rel=1e-12)
    again = closed_loop(delta_run, "cem", steps=12, episodes=2, seed=3, overrides=small, device="cpu")
    assert again["rewards"] == res["rewards"]
    assert hashlib.sha256(ckpt.read_bytes()).hexdigest() == before
    out = tmp_path / "c.json"
    code = warm.run(
        [sys.executable, "-m", "pets.openloop", "--run", str(delta_run), "--closed-loop", "--steps", "4",
         "--episodes", "1", "--quiet", "--json", str(out), *(f"{k}={v}" for k, v in small.items())],
        capture_output=True, text=True,
    )  # fmt: skip
    assert code.returncode == 0, code.stderr
    assert "closed loop: reacher" in code.stdout and json.loads(out.read_text())["steps"] == 4


def test_training_on_too_few_transitions_for_a_holdout_says_so_instead_of_nan(tmp_path):
    data = tmp_path / "tiny.npz"
    run("pets.collect", "--env", "reacher", "--policy", "random", "--episodes", 1, "--max-steps", 2, "--out", data)
    proc = run("pets.train", "--data", data, "--model", "delta", "--out", tmp_path / "run", "--epochs", 1, "--quiet")
    assert "no holdout error (too few transitions to hold any out" in proc.stdout and "nan" not in proc.stdout
