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
    with pytest.raises(ValueError, match=r"has no such name; did you mean tests\.custom_envs:PENDULUM\?"):
        envs.get("tests.custom_envs:PENDULM")  # a typo of the attribute


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
    # the summary finds the runs' evaluations (their request names the data file by the spec's name)
    assert {(r["env"], r["model"]) for r in result["summary"]} == {(PATH, "delta"), (PATH, "gem")}
    assert "Missing runs" not in (tmp_path / "prediction.md").read_text()


def test_a_registered_spec_through_the_python_api():
    layout = ObsLayout(obs_dim=3, groups=(Group("pole", "SO2_cossin", (0, 1)),), velocities=(2,))
    envs.register(envs.custom_spec("my-pendulum", "Pendulum-v1", layout, pendulum_reward))
    with one_thread():
        agent = pets.PETS("my-pendulum", model="gem", preset="fast", seed_steps=100, episode_length=30)
        agent.learn(trials=1)
    assert agent.trials_done == 1 and agent.config.env == "my-pendulum"


def test_a_name_registered_to_another_spec_is_refused_not_replaced():
    layout = ObsLayout(obs_dim=3, groups=(Group("pole", "SO2_cossin", (0, 1)),), velocities=(2,))
    first = envs.register(envs.custom_spec("my-pendulum", "Pendulum-v1", layout, pendulum_reward))
    assert envs.register(first) is first  # the same spec again: nothing changes
    other = envs.custom_spec("my-pendulum", "Pendulum-v1", layout, pendulum_reward, episode_length=50)
    with pytest.raises(ValueError, match="'my-pendulum' is registered to another spec in this process"):
        envs.register(other)
    assert envs.get("my-pendulum") is first


def test_a_spec_that_does_not_fit_its_env_is_refused_in_one_line():
    wide = ObsLayout(obs_dim=4, groups=(Group("pole", "SO2_cossin", (0, 1)),), velocities=(2, 3))
    with pytest.raises(ValueError, match="the layout covers 4 observation entries, Pendulum-v1 has 3"):
        envs.custom_spec("p", "Pendulum-v1", wide, pendulum_reward)
    layout = ObsLayout(obs_dim=3, groups=(Group("pole", "SO2_cossin", (0, 1)),), velocities=(2,))
    with pytest.raises(ValueError, match=r"reward_fn must return a tensor of shape \(batch,\)"):
        envs.custom_spec("p", "Pendulum-v1", layout, lambda o, a, n: o)
    with pytest.raises(ValueError, match="catalogue env"):
        envs.register(envs.custom_spec("reacher", "Pendulum-v1", layout, pendulum_reward))


@pytest.mark.parametrize(
    "change, fragment",
    [
        ({"episode_length": -5}, "episode_length must be a positive int (or None: the env's), got -5"),
        ({"episode_length": 2.5}, "episode_length must be a positive int"),
        ({"episode_length": True}, "episode_length must be a positive int"),
        ({"layout": None}, "layout must be an envs.ObsLayout, got NoneType"),
        ({"name": ""}, "custom_spec: name must be a non-empty string without ':', '/' or '\\', got ''"),
        ({"name": 3}, "custom_spec: name must be a non-empty string"),
        ({"name": "my:pendulum"}, "without ':'"),  # an import path's separator
        ({"name": "runs/pendulum"}, "without ':', '/'"),  # run directories are named by it
        ({"reward_fn": 3}, "reward_fn must be a function (obs, act, next_obs) -> tensor, got 3"),
        ({"terminated_fn": "never"}, "terminated_fn must be a function"),
        ({"reward_fn": lambda o, a, n: pendulum_reward(o, a, n) * torch.nan, "reward_differs": True},
         "reward_fn returned nan or inf on a real transition"),
        ({"env_kwargs": {"g": "x"}}, "p: Pendulum-v1 failed to reset or step (TypeError: "),
    ],
)  # fmt: skip
def test_a_spec_argument_of_the_wrong_kind_is_one_line_before_any_run(change, fragment):
    """Each was accepted, then failed deep inside a run (a traceback from run_pets.py for a negative episode length,
    a planning error blaming the model for a NaN reward) or raised an AttributeError; a shaped reward
    (reward_differs) may differ from the env's, never be non-finite."""
    layout = ObsLayout(obs_dim=3, groups=(Group("pole", "SO2_cossin", (0, 1)),), velocities=(2,))
    kwargs = {"name": "p", "gym_id": "Pendulum-v1", "layout": layout, "reward_fn": pendulum_reward, **change}
    with pytest.raises(ValueError) as err:
        envs.custom_spec(**kwargs)
    assert fragment in str(err.value) and "\n" not in str(err.value)


def test_a_name_that_spells_a_catalogue_env_cannot_be_registered():
    """``Reacher`` or ``Reacher-v5`` would have shadowed the catalogue's Reacher for the whole process."""
    layout = ObsLayout(obs_dim=3, groups=(Group("pole", "SO2_cossin", (0, 1)),), velocities=(2,))
    for name in ("Reacher", "Reacher-v5", "half_cheetah"):
        with pytest.raises(ValueError, match=r"names the catalogue env (reacher|halfcheetah) \("):
            envs.register(envs.custom_spec(name, "Pendulum-v1", layout, pendulum_reward))
        assert envs.get(name).gym_id in ("Reacher-v5", "HalfCheetah-v5")


def test_a_video_of_an_env_that_is_not_mujoco_is_one_line_and_leaves_no_directory(tmp_path):
    """Was an AttributeError traceback (exit 1) and a directory holding only the lock."""
    proc = cli("--env", PATH, "--video", 1, "--trials", 1, *SMALL, "--out", tmp_path / "run", check=False)
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "videos are rendered by MuJoCo; " in lines[0] and "is not a MuJoCo env: drop --video" in lines[0]
    assert not (tmp_path / "run").exists()


def test_a_video_of_an_env_that_is_not_mujoco_says_drop_video_even_without_imageio(monkeypatch):
    """The env's kind is checked first: without the viz extra the line said to install imageio, which would not
    help (seen on a machine without imageio-ffmpeg, 2026-12-01)."""
    import sys

    from pets.errors import ConfigError
    from pets.runs.video import EpisodeRecorder

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # as if not installed: its import fails
    spec = envs.get(PATH)
    with pytest.raises(ConfigError, match="is not a MuJoCo env: drop --video"):
        EpisodeRecorder(spec, spec.make())


def test_pets_collect_takes_the_import_path_as_its_help_says(tmp_path):
    """pets.collect --env module:ATTR collects the spec's env (its --help says so), the file names the path."""
    from pets.data.datasets import load_dataset
    from pets.tools.collect import build_parser, main

    assert "module:ATTR" in build_parser().format_help()
    out = tmp_path / "d.npz"
    assert main(["--env", PATH, "--policy", "random", "--episodes", "1", "--max-steps", "5", "--out", str(out)]) == 0
    assert str(load_dataset(out)["env"]) == PATH
