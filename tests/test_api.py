"""The Python API (pets.api, docs/api.md): a saved and reloaded object continues exactly as the object that was not
saved; the model's predict/rollout against the planner's own decoding; one-line errors. Every example of docs/api.md
runs as written from the installed wheel (tests/test_packaging.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import pets
from pets.config import ConfigError
from pets.runs import rundir
from tests.test_cli import cli, rows
from tests.threads import one_thread

TINY = {
    "seed_steps": 100,
    "episode_length": 20,
    "planner.population": 16,
    "planner.horizon": 5,
    "model.hidden_size": 32,
}


def test_a_saved_and_loaded_object_continues_as_the_one_never_saved(tmp_path):
    with one_thread():
        a = pets.PETS("invertedpendulum", model="delta", preset="fast", seed=4, **TINY, **{"value.steps": 20})
        a.learn(trials=1)
        a.save(tmp_path / "run")
        b = pets.PETS.load(tmp_path / "run")
        a.learn(trials=1)
        b.learn(trials=1)
    timing = rundir.TIMING_COLUMNS
    strip = [{k: v for k, v in row.items() if k not in timing} for row in (a.history[-1], b.history[-1])]
    assert strip[0] == strip[1] and b.trials_done == 2
    for p, q in zip(a.model.state_dict().values(), b.model.state_dict().values()):
        assert torch.equal(p, q)


def test_learn_gives_run_pets_metrics_of_the_same_settings_seed_and_trials(tmp_path):
    """docs/api.md: ``PETS(..., seed=S, trials=N).learn()`` gives ``run_pets.py --seed S --trials N`` with the same
    settings, every column of metrics.csv but the timings bit for bit."""
    settings = {**TINY, "value.steps": 20}
    keys = [f"{key}={value}" for key, value in settings.items()]
    run = tmp_path / "run"
    args = ["--env", "invertedpendulum", "--model", "delta", "--preset", "fast", "--seed", 4, "--trials", 2]
    cli(*args, "--out", run, "--quiet", "threads=1", *keys)
    with one_thread():
        api = pets.PETS("invertedpendulum", model="delta", preset="fast", seed=4, trials=2, **settings).learn()
    timing = rundir.TIMING_COLUMNS
    want = [{k: v for k, v in row.items() if k not in timing} for row in rows(run)]
    assert [{k: str(v) for k, v in row.items() if k not in timing} for row in api.history] == want


def test_learn_stops_where_the_run_is_done_as_run_pets_does():
    """An env-step budget (``--preset locomotion``'s 100k, here 200) ends learn() before its trials, as it ends
    run_pets.py; learning on after it does nothing (it raised "max_steps must be a positive int, got 0"), and a
    trial at ``stop_reward`` ends it too."""
    small = {**TINY, "value.steps": 20, "model.iterations": 5, "model.compile": False, "train_every": 100}
    with one_thread():
        budget = pets.PETS("invertedpendulum", model="delta", preset="locomotion", max_env_steps=200, **small)
        budget.learn(trials=100)
        done = budget.trials_done
        assert 1 < done < 100 and budget.history[-1]["env_steps"] == 200
        assert budget.learn().learn(trials=5).trials_done == done
        reward = pets.PETS("invertedpendulum", model="delta", preset="fast", stop_reward=1.0, **small)
        assert reward.learn(trials=5).trials_done == 1  # every episode earns at least 1


def test_predict_is_the_models_own_decoding_and_types_follow_the_input(tmp_path):
    with one_thread():
        agent = pets.PETS("reacher", model="gem", preset="fast", seed=1, **TINY)
        agent.learn(trials=1)
    agent.save(tmp_path / "run")
    model = pets.load_model(tmp_path / "run")
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(2, 3, model.obs_dim)).astype(np.float32)
    act = rng.uniform(-1, 1, size=(2, 3, model.act_dim)).astype(np.float32)
    got = model.predict(obs, act)
    assert isinstance(got, np.ndarray) and got.shape == (2, 3, model.obs_dim)
    o, a = torch.as_tensor(obs).reshape(6, -1), torch.as_tensor(act).reshape(6, -1)
    with torch.no_grad():
        mean, _ = model(model.inputs(o, a), model.elites)
        want = model.next_obs(o, mean.mean(0)).reshape(2, 3, -1)
    torch.testing.assert_close(torch.as_tensor(got), want)
    assert isinstance(model.predict(o, a), torch.Tensor)
    with pytest.raises(ValueError, match="expected observations"):
        model.predict(obs[..., :3], act)
    nan_obs = obs.copy()
    nan_obs[1, 2, 0] = np.nan
    for bad in ((nan_obs, act), (obs, np.full_like(act, np.inf))):  # were: nan predictions, no error
        with pytest.raises(ValueError, match="hold nan or inf; the model predicts from finite inputs only"):
            model.predict(*bad)
    with pytest.raises(ValueError, match="generator must be a torch.Generator"):
        model.predict(obs, act, mode="sample", generator=0)
    with pytest.raises(ValueError, match=r"observations \(2, 3, \d+\) and actions \(2, 2, \d+\): batch dims differ"):
        model.predict(obs, act[:, :2])  # the shapes given, not the internal (..., 1, act_dim)
    with pytest.raises(ValueError, match=r"actions need a horizon axis, \(\.\.\., H, act_dim\); predict takes one"):
        model.rollout(obs, act)
    for device, fragment in (("gpu", "device must be one of auto, cpu, cuda"), ("cuda", "no CUDA device")):
        if device == "cuda" and torch.cuda.is_available():
            continue  # the machine has one: load_model takes it
        with pytest.raises(ConfigError, match=fragment):  # were: torch's own RuntimeError / AssertionError
            pets.load_model(tmp_path / "run", device=device)


def test_bad_input_is_one_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="unknown env 'nope'"):
        pets.PETS("nope")
    with pytest.raises(ConfigError, match="unknown config key 'planner.nope'"):
        pets.PETS("reacher", **{"planner.nope": 1})
    with pytest.raises(ConfigError, match="gem-se composes a floating root"):
        pets.PETS("reacher", model="gem-se")
    with pytest.raises(ConfigError, match="not a run directory"):
        pets.PETS.load("/nonexistent-run")
    (tmp_path / "killed").mkdir()  # a run killed (kill -9) before it wrote its config: only its lock is left
    (tmp_path / "killed" / ".lock").write_text("12345\n")
    with pytest.raises(ConfigError, match="holds no run"):
        pets.PETS.load(tmp_path / "killed")
    with pytest.raises(ValueError, match="trials must be a positive int"):
        pets.PETS("reacher", preset="fast").learn(trials=0)
    agent = pets.PETS("invertedpendulum", preset="fast", threads=1)
    obs = np.zeros(4)
    for bad, fragment in (
        ((obs, {}), r"act takes the observation, not reset\(\)'s \(obs, info\) pair"),
        (np.array([0.0, np.nan, 0.0, 0.0]), r"obs holds nan or inf at entries \[1\]"),  # was: blamed the model
        ("hello", "obs must be an array of numbers, got str"),
    ):
        with pytest.raises(ValueError, match=fragment):
            agent.act(bad)
    orphan = tmp_path / "orphan"  # a checkpoint without its config.yaml: another run's, never written over
    orphan.mkdir()
    (orphan / "checkpoint.pt").write_bytes(b"trials_done=7")
    with pytest.raises(ConfigError, match="already holds a run"):
        agent.save(orphan)
    assert (orphan / "checkpoint.pt").read_bytes() == b"trials_done=7"
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ConfigError, match="afile is a file; save to a directory"):  # was: FileExistsError, errno 17
        agent.save(tmp_path / "afile")
