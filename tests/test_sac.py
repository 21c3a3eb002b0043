"""Data like the GEM paper's: SAC (stable-baselines3) training data and rollouts of a saved SB3 agent.

Ground truth: SB3's own replay buffer (what SAC trained on) and the real MuJoCo envs. Tiny budgets: SAC learns
after ``learning_starts`` = 100 steps, so a few hundred steps exercise learning and recording.
"""

import math
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

import envs
from pets.data.collect import collect, collect_sac, make_policy
from pets.data.datasets import load_dataset, transitions
from tests import warm
from tests.threads import one_thread

pytest.importorskip("stable_baselines3", reason='the sac extra is part of .[dev]: pip install -e ".[dev]"')

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
STEPS = 300


def collect_cli(*args, check=True):
    proc = warm.run(
        [sys.executable, "-m", "pets.collect", *map(str, args), "--threads", "1", "--quiet"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env=ENV,
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"pets.collect exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


@pytest.fixture(scope="module", params=["invertedpendulum", "ant"])
def sac_run(request, tmp_path_factory):
    """``pets.collect --policy sac:300 --save-agent`` then ``--policy sb3:`` test episodes, by the command line."""
    name = request.param
    work = tmp_path_factory.mktemp(f"sac-{name}")
    train = collect_cli("--env", name, "--policy", f"sac:{STEPS}", "--out", work / "train.npz", "--save-agent",
                        work / "sac.zip", "--max-steps", 60)  # fmt: skip
    test = collect_cli("--env", name, "--policy", f"sb3:{work / 'sac.zip'}", "--episodes", 3, "--out",
                       work / "test.npz", "--max-steps", 40)  # fmt: skip
    return name, work, train, test


def test_sac_and_sb3_commands_write_data_sets_the_loader_reads(sac_run):
    name, work, train, test = sac_run
    spec = envs.get(name)
    data = load_dataset(work / "train.npz")  # validates format, padding and finiteness
    assert str(data["env"]) == name and str(data["policy"]) == f"sac:{STEPS}"
    assert int(data["lengths"].sum()) == STEPS  # every step SAC took, nothing more
    assert data["obs"].shape[-1] == spec.obs_dim and data["act"].shape[-1] == spec.act_dim
    assert int(data["lengths"].max()) <= 60
    # episodes end where the env said so: terminated only at an episode's last step
    term_steps = np.argwhere(data["terminated"])
    np.testing.assert_array_equal(term_steps[:, 1], data["lengths"][term_steps[:, 0]] - 1)
    assert "SAC: 300 steps" in train.stdout and "agent saved" in train.stdout
    assert (work / "sac.zip").is_file()
    test_data = load_dataset(work / "test.npz")
    assert len(test_data["lengths"]) == 3 and str(test_data["policy"]) == "sb3:sac.zip"
    obs, act, _ = transitions(test_data)
    assert np.all(act >= np.array(spec.action_low) - 1e-9) and np.all(act <= np.array(spec.action_high) + 1e-9)


@pytest.fixture
def threads1():
    with one_thread():
        yield


def test_recorded_transitions_are_exactly_what_sac_trained_on(threads1):
    """The recorder (a wrapper under SB3) and SB3's replay buffer must hold the same transitions, in order."""
    spec = envs.get("invertedpendulum")
    data, agent = collect_sac(spec, 250, seed=3, max_steps=40)
    obs, act, next_obs = transitions(data)
    buf = agent.replay_buffer
    n = buf.pos
    assert n == 250 == len(obs)
    np.testing.assert_array_equal(buf.observations[:n, 0], obs.astype(buf.observations.dtype))
    np.testing.assert_array_equal(buf.next_observations[:n, 0], next_obs.astype(buf.next_observations.dtype))
    rew = data["rew"][~np.isnan(data["rew"])]
    np.testing.assert_allclose(buf.rewards[:n, 0], rew, rtol=0, atol=1e-6)
    np.testing.assert_allclose(agent.policy.unscale_action(buf.actions[:n, 0]), act, rtol=0, atol=1e-5)
    # SB3 marks true terminations as done (timeouts are not): the same steps as our terminated flags
    term = data["terminated"][np.arange(data["act"].shape[1])[None, :] < data["lengths"][:, None]]
    done = buf.dones[:n, 0].astype(bool) & ~buf.timeouts[:n, 0].astype(bool)
    np.testing.assert_array_equal(done, term)


def test_sac_data_is_reproducible_and_sb3_rollouts_replay_in_the_simulator(tmp_path, threads1):
    spec = envs.get("invertedpendulum")
    a, agent = collect_sac(spec, 150, seed=1, max_steps=30)
    b, _ = collect_sac(spec, 150, seed=1, max_steps=30)
    for key in ("obs", "act", "rew", "lengths"):
        np.testing.assert_array_equal(a[key], b[key])
    agent.save(tmp_path / "agent.zip")
    stochastic = collect(spec, make_policy(f"sb3:{tmp_path / 'agent.zip'}", spec), 2, seed=4, max_steps=20)
    again = collect(spec, make_policy(f"sb3:{tmp_path / 'agent.zip'}", spec), 2, seed=4, max_steps=20)
    np.testing.assert_array_equal(stochastic["act"], again["act"])
    mean = collect(spec, make_policy(f"sb3:{tmp_path / 'agent.zip'}", spec, deterministic=True), 2, 4, 20)
    expected, _ = agent.predict(mean["obs"][0, :1], deterministic=True)
    np.testing.assert_allclose(mean["act"][0, 0], expected[0], atol=1e-6)
    # replaying the recorded actions from the recorded reset seed reproduces the observations
    env = spec.make()
    o, _ = env.reset(seed=int(mean["reset_seeds"][0]))
    np.testing.assert_allclose(o, mean["obs"][0, 0])
    for t in range(int(mean["lengths"][0])):
        o, *_ = env.step(mean["act"][0, t])
        np.testing.assert_allclose(o, mean["obs"][0, t + 1], atol=1e-9)


def test_collect_rejects_bad_sb3_arguments_in_one_line(tmp_path, sac_run):
    name, work, _, _ = sac_run
    other = "ant" if name == "invertedpendulum" else "invertedpendulum"
    cases = [
        (["--env", name, "--policy", "sac:0", "--out", tmp_path / "x.npz"], "positive number of env steps"),
        (["--env", name, "--policy", "sac:100", "--episodes", 3, "--out", tmp_path / "x.npz"], "--episodes"),
        (
            ["--env", name, "--policy", "random", "--save-agent", tmp_path / "a.zip", "--out", tmp_path / "x.npz"],
            "--save-agent applies only",
        ),  # fmt: skip
        (["--env", name, "--policy", f"sb3:{tmp_path / 'none.zip'}", "--out", tmp_path / "x.npz"], "does not exist"),
        (["--env", other, "--policy", f"sb3:{work / 'sac.zip'}", "--out", tmp_path / "x.npz"], "trained on"),
        (["--env", name, "--policy", f"sb3:{work / 'train.npz'}", "--out", tmp_path / "x.npz"], "SB3 agent"),
    ]
    for args, message in cases:
        proc = collect_cli(*args, check=False)
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        assert proc.returncode == 2, (args, proc.stderr)
        assert len(lines) == 1 and message in lines[0], (args, proc.stderr)
    assert not (tmp_path / "x.npz").exists()


def test_compare_offline_with_sac_data_and_the_paper_protocol(tmp_path):
    """`pets.compare offline --policy sac:STEPS --protocol paper`: SAC training data, SB3 test episodes, the paper's
    training with its hidden-layer search, evaluation; a rerun reuses everything."""
    out = tmp_path / "cmp"
    args = [sys.executable, "-m", "pets.compare", "offline", "--envs", "invertedpendulum", "--models", "delta,gem",
            "--seeds", "0,1", "--out", str(out), "--policy", "sac:200", "--protocol", "paper", "--test-episodes", "2",
            "--max-steps", "30", "--starts", "10", "--horizons", "1,5", "--quiet", "model.iterations=30"]  # fmt: skip
    proc = warm.run(args, cwd=ROOT, capture_output=True, text=True, timeout=600, env=ENV)
    assert proc.returncode == 0, proc.stderr
    train, test = (
        load_dataset(out / "data/invertedpendulum-train.npz"),
        load_dataset(out / "data/invertedpendulum-test.npz"),
    )
    assert str(train["policy"]) == "sac:200" and int(train["lengths"].sum()) == 200
    assert str(test["policy"]) == "sb3:invertedpendulum-sac.zip" and len(test["lengths"]) == 2
    from pets.config import load_config
    from pets.runs import rundir

    for model in ("delta", "gem"):
        run = out / "runs" / f"invertedpendulum-{model}-s1"
        cfg = load_config(str(run / "config.yaml"))
        assert (cfg.model.lr, cfg.model.batch_size, cfg.model.iterations, cfg.model.bootstrap) == (5e-4, 10, 30, False)
        offline = rundir.load_checkpoint(run)["offline"]
        assert offline["protocol"] == "paper" and len(offline["search"]) == 3
        assert (run / "eval.json").is_file()
    again = warm.run(args, cwd=ROOT, capture_output=True, text=True, timeout=600, env=ENV)
    assert again.returncode == 0 and "4 reused, 0 with work to do" in again.stderr, again.stderr


def test_paper_protocol_trains_and_evaluates_on_the_sac_data(sac_run):
    """`pets.train --protocol paper` then `pets.evaluate --train-data` on the SAC files, by the command line."""
    import json

    name, work, _, _ = sac_run
    run_dir = work / "paper-gem"
    train = warm.run(
        [sys.executable, "-m", "pets.train", "--data", str(work / "train.npz"), "--model", "gem", "--protocol",
         "paper", "--out", str(run_dir), "--quiet", "model.iterations=5", "threads=1"],
        cwd=ROOT, capture_output=True, text=True, timeout=300, env=ENV,
    )  # fmt: skip
    assert train.returncode == 0, train.stderr
    width = 512 if name == "ant" else 100  # the paper searched [512] x 1..3 for Ant and Humanoid
    assert [f"hidden layers {n} x {width}" in train.stdout for n in (1, 2, 3)] == [True] * 3
    evaluate = warm.run(
        [sys.executable, "-m", "pets.evaluate", "--run", str(run_dir), "--data", str(work / "test.npz"),
         "--train-data", str(work / "train.npz"), "--horizons", "1,5", "--starts", "20", "--json",
         str(work / "eval.json"), "--threads", "1"],
        cwd=ROOT, capture_output=True, text=True, timeout=300, env=ENV,
    )  # fmt: skip
    assert evaluate.returncode == 0, evaluate.stderr
    result = json.loads((work / "eval.json").read_text())
    row = result["horizons"]["1"]
    assert result["model"] == "gem" and result["standardized_by"] == str(work / "train.npz")
    assert all(np.isfinite(row[k]) for k in ("mean_step_error", "rotation_error", "standardized_error"))
    if name == "ant":  # the torso quaternion is a rotation group: a geodesic angle, never NaN
        assert row["rotation_error"] > 0


def test_sac_collection_goes_on_from_its_checkpoint(tmp_path, threads1, monkeypatch):
    """A SAC collection writes a checkpoint (agent, replay buffer, episodes) every ``checkpoint_every`` steps; run
    again with the same settings it goes on from there: the steps before it are the uninterrupted run's, SB3's
    replay buffer still holds every recorded transition, the running episode ends at the checkpoint, and the data
    set says where it was resumed. Other settings are refused in one line. Neither the new agent nor the resumed one
    leaves SB3's logger folder (an empty ``SB3-<date>``) in the temporary directory."""
    import tempfile

    from pets.data.collect import pack_episodes
    from pets.data.sb3 import read_sac_checkpoint, train_sac

    temp = tmp_path / "temp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))  # what SB3's logger asks tempfile.gettempdir() for
    spec, ckpt = envs.get("invertedpendulum"), tmp_path / "ip-train.npz.sac-checkpoint"
    whole, ref, resumed_at = train_sac(spec, 260, seed=2, max_steps=5, checkpoint=ckpt, checkpoint_every=150)
    assert resumed_at == [] and ckpt.is_file()  # the one at step 150 (none at the end: the caller saves the data)
    assert read_sac_checkpoint(ckpt, read_settings(ckpt))["steps_done"] == 150
    data, agent = collect_sac(spec, 260, seed=2, max_steps=5, checkpoint=ckpt)
    assert data["sac_resumed_at"].tolist() == [150]
    obs, act, next_obs = transitions(data)
    first = transitions(pack_episodes(spec, whole, "sac:260", 2))[0][:150]
    np.testing.assert_array_equal(obs[:150], first)  # before the checkpoint: the uninterrupted run's steps
    assert len(obs) == 260 and agent.num_timesteps == 260 and agent.replay_buffer.pos == 260
    buf = agent.replay_buffer  # it holds every recorded transition, the ones before the checkpoint included
    np.testing.assert_array_equal(buf.observations[:260, 0], obs.astype(buf.observations.dtype))
    for key in ("observations", "next_observations", "rewards", "dones", "timeouts"):  # refilled as SB3 stores
        np.testing.assert_array_equal(getattr(buf, key)[:150], getattr(ref.replay_buffer, key)[:150], err_msg=key)
    np.testing.assert_allclose(buf.actions[:150], ref.replay_buffer.actions[:150], rtol=0, atol=1e-6)
    assert ref.replay_buffer.dones[:150].any() and ref.replay_buffer.timeouts[:150].any()  # both kinds of end
    ends = np.cumsum(data["lengths"])
    assert 150 in ends  # the episode running at the checkpoint ends there (the env was reset)
    again, _ = collect_sac(spec, 260, seed=2, max_steps=5, checkpoint=ckpt)  # the same checkpoint: the same data
    for key in ("obs", "act", "rew", "lengths"):
        np.testing.assert_array_equal(again[key], data[key])
    assert list(temp.iterdir()) == []
    with pytest.raises(ValueError, match=r"other settings \(seed: 2 != 3\); delete it"):
        collect_sac(spec, 260, seed=3, max_steps=5, checkpoint=ckpt)
    ckpt.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="cannot read the SAC checkpoint .* delete it to start over"):
        collect_sac(spec, 260, seed=2, max_steps=5, checkpoint=ckpt)


def read_settings(path):
    import pickle

    with open(path, "rb") as f:
        return pickle.load(f)["settings"]


def test_collect_cli_deletes_the_sac_checkpoint_once_the_data_are_written(tmp_path):
    out = tmp_path / "ip.npz"
    ckpt = out.with_name("ip.npz.sac-checkpoint")
    ckpt.write_bytes(b"stale")  # an unreadable checkpoint: refused in one line, nothing written
    bad = collect_cli("--env", "invertedpendulum", "--policy", "sac:120", "--max-steps", 30, "--out", out, check=False)
    assert bad.returncode == 2 and "cannot read the SAC checkpoint" in bad.stderr and "Traceback" not in bad.stderr
    assert not out.exists()
    ckpt.unlink()
    collect_cli("--env", "invertedpendulum", "--policy", "sac:120", "--max-steps", 30, "--out", out)
    assert out.is_file() and not ckpt.exists() and "sac_resumed_at" not in load_dataset(out)


def test_the_locomotion_gate_reads_sac_episodes_from_a_sac_collection(sac_run, tmp_path):
    """SAC's reference row of the gate (gate_references.sac_run, gate.reference_row): the episodes SAC trained on."""
    from pets.experiments import gate, gate_references

    def sac_row(path):
        return gate.reference_row(gate_references.sac_run(path))

    name, work, _, _ = sac_run
    data = load_dataset(work / "train.npz")
    row = sac_row(work / "train.npz")
    assert row["env"] == name and row["agent"] == "sac" and row["env_steps"] == STEPS
    assert row["episodes"] == len(data["lengths"]) and row["status"] == "partial"  # 300 of 100k steps
    assert row["fall_fraction"] == pytest.approx(float(data["terminated"].any(axis=1).mean()), abs=1e-4)
    assert math.isnan(row["cpu_hours"])  # nothing recorded its CPU time
    copy = tmp_path / "train.npz"
    shutil.copy(work / "train.npz", copy)
    copy.with_suffix(".cpu_s").write_text("5400.0\n")  # the collection's CPU seconds, written beside it
    assert sac_row(copy)["cpu_hours"] == 1.5
