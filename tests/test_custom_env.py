"""Your own env (envs.custom): gymnasium's Pendulum-v1 as a user would add it (tests/custom_envs.py), its reward
against the simulator's, through run_pets.py (start, resume), pets.load_model, pets.compare offline and the Python
API; one-line errors for a spec that does not fit its env."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import envs
import pets
from envs import Group, ObsLayout
from tests.custom_envs import pendulum_reward
from tests.test_cli import cli, error_lines, rows
from tests.threads import one_thread

PATH = "tests.custom_envs:PENDULUM"
SMALL = [
    "--preset",
    "fast",
    "threads=1",
    "seed_steps=100",
    "episode_length=40",
    "planner.population=20",
    "model.hidden_size=32",
]


def test_the_reward_is_the_simulators():
    spec = envs.get(PATH)
    assert (spec.name, spec.obs_dim, spec.act_dim, spec.episode_length) == (PATH, 3, 1, 200)
    env = spec.make()
    obs, _ = env.reset(seed=3)
    for _ in range(300):
        act = env.action_space.sample() * 1.5  # beyond the bounds too: the reward clips the torque as the env does
        nxt, reward, *_ = env.step(act)
        got = spec.reward(*(torch.as_tensor(x, dtype=torch.float64)[None] for x in (obs, act, nxt)))
        assert float(got[0]) == pytest.approx(reward, abs=1e-5)  # the observation is float32 (cos, sin)
        obs = nxt
    assert not spec.terminated(torch.zeros(4, 3), torch.zeros(4, 1), torch.zeros(4, 3)).any()


def test_an_import_path_runs_resumes_and_loads_in_a_new_process(tmp_path):
    out = tmp_path / "run"
    cli("--env", PATH, "--model", "gem", "--trials", 2, "--out", out, *SMALL)
    cli("--resume", out, "--trials", 3)
    assert [int(r["trial"]) for r in rows(out)] == [0, 1, 2]
    model = pets.load_model(out)
    assert model.name == "gem" and model.predict(np.zeros((5, 3)), np.zeros((5, 1))).shape == (5, 3)
    proc = cli("--env", "tests.custom_envs:NOPE", "--out", tmp_path / "x", check=False)
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1 and "cannot import 'NOPE' from 'tests.custom_envs'" in lines[0]


def test_pets_compare_offline_takes_the_import_path(tmp_path):
    from pets.experiments.offline import compare_offline

    result = compare_offline(
        [PATH],
        ["delta", "gem"],
        [0],
        tmp_path,
        episodes=3,
        test_episodes=2,
        horizons=[1, 5],
        starts=10,
        preset="fast",
        device="cpu",
        overrides=["model.hidden_size=32", "model.max_epochs=3"],
        progress=False,
    )
    assert not result["failed"] and set(result["done"]) == {"pendulum-delta-s0", "pendulum-gem-s0"}  # no colon


def test_a_registered_spec_through_the_python_api():
    layout = ObsLayout(obs_dim=3, groups=(Group("pole", "SO2_cossin", (0, 1)),), velocities=(2,))
    envs.register(envs.custom_spec("my-pendulum", "Pendulum-v1", layout, pendulum_reward))
    with one_thread():
        agent = pets.PETS("my-pendulum", model="gem", preset="fast", seed_steps=100, episode_length=30)
        agent.learn(trials=1)
    assert agent.trials_done == 1 and agent.config.env == "my-pendulum"


def test_a_spec_that_does_not_fit_its_env_is_refused_in_one_line():
    wide = ObsLayout(obs_dim=4, groups=(Group("pole", "SO2_cossin", (0, 1)),), velocities=(2, 3))
    with pytest.raises(ValueError, match="the layout covers 4 observation entries, Pendulum-v1 has 3"):
        envs.custom_spec("p", "Pendulum-v1", wide, pendulum_reward)
    layout = ObsLayout(obs_dim=3, groups=(Group("pole", "SO2_cossin", (0, 1)),), velocities=(2,))
    with pytest.raises(ValueError, match=r"reward_fn must return a tensor of shape \(batch,\)"):
        envs.custom_spec("p", "Pendulum-v1", layout, lambda o, a, n: o)
    with pytest.raises(ValueError, match="catalogue env"):
        envs.register(envs.custom_spec("reacher", "Pendulum-v1", layout, pendulum_reward))
