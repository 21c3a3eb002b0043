"""Your own env from your own folder (issue 55): ``--env mymodule:SPEC`` imports from where the command runs, in
run_pets.py and in pets.compare's child processes; directories and files go by the spec's name (no colon); a spec
that raises, names an unknown gym id, has the wrong act_dim or a reward that is not the env's is one line."""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import envs
from envs import Group, ObsLayout
from tests.custom_envs import pendulum_reward

ROOT = Path(__file__).resolve().parents[1]
SPEC_MODULE = (ROOT / "tests" / "custom_envs.py").read_text().replace("PENDULUM = pendulum()", "SPEC = pendulum()")
SMALL = [
    "--preset",
    "fast",
    "threads=1",
    "seed_steps=50",
    "episode_length=20",
    "planner.population=16",
    "planner.horizon=4",
    "model.hidden_size=32",
    "model.max_epochs=2",
]
LAYOUT = ObsLayout(obs_dim=3, groups=(Group("pole", "SO2_cossin", (0, 1)),), velocities=(2,))


def _user_folder(tmp_path: Path, **modules: str) -> Path:
    folder = tmp_path / "me"
    folder.mkdir(exist_ok=True)
    (folder / "mypend.py").write_text(SPEC_MODULE)
    for name, text in modules.items():
        (folder / f"{name}.py").write_text(text)
    return folder


def _command(args: list[str], cwd: Path, module: bool = False) -> subprocess.CompletedProcess:
    """A command as a user runs it in ``cwd``: ``python ROOT/run_pets.py`` (nothing on PYTHONPATH), or ``python -m``
    with the package importable (PYTHONPATH: the repository, as an installed package is)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if module:
        env["PYTHONPATH"] = str(ROOT)
        cmd = [sys.executable, "-m", *args]
    else:
        cmd = [sys.executable, str(ROOT / "run_pets.py"), *args]
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def _one_error(proc: subprocess.CompletedProcess) -> str:
    lines = [line for line in proc.stderr.splitlines() if line.strip() and not line.startswith("run directory:")]
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    return lines[0]


def _names(top: Path) -> list[str]:
    return [str(p.relative_to(top)) for p in top.rglob("*")]


def test_run_pets_imports_your_env_from_your_folder_and_names_files_without_a_colon(tmp_path):
    me = _user_folder(tmp_path)
    proc = _command(["--env", "mypend:SPEC", "--model", "gem", "--trials", "1", "--quiet", *SMALL], me)
    assert proc.returncode == 0, proc.stderr
    (run,) = (me / "runs").iterdir()
    assert run.name.startswith("pendulum-gem-s0-") and not any(":" in n for n in _names(me / "runs"))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    line = _one_error(_command(["--resume", str(run), "--trials", "2"], elsewhere))
    assert "cannot import 'SPEC' from 'mypend'" in line
    assert "run the command from the folder that holds mypend.py" in line
    assert _command(["--resume", str(run), "--trials", "2", "--quiet"], me).returncode == 0


def test_pets_compare_runs_your_env_from_your_folder_in_every_child(tmp_path):
    me = _user_folder(tmp_path)
    args = ["pets.compare", "online", "--envs", "mypend:SPEC", "--models", "delta", "--seeds", "0", "--trials", "1"]
    proc = _command([*args, "--out", "cmp", "--quiet", *SMALL], me, module=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = me / "cmp"
    assert (out / "runs" / "pendulum-delta-s0" / "metrics.csv").is_file() and (out / "rewards_pendulum.png").is_file()
    assert not any(":" in n for n in _names(out))


def test_two_envs_with_one_name_are_refused_by_pets_compare(tmp_path):
    me = _user_folder(tmp_path, other=SPEC_MODULE)
    args = ["pets.compare", "online", "--envs", "mypend:SPEC,other:SPEC", "--models", "delta", "--trials", "1"]
    args += ["--out", "cmp"]
    line = _one_error(_command(args, me, module=True))
    assert "both go by the name 'pendulum'" in line


SPEC_ERRORS = {
    "raises": ("raise RuntimeError('no licence here')\n", "importing 'bad' failed (RuntimeError: no licence here)"),
    "syntax": ("def (:\n", "importing 'bad' failed (SyntaxError"),
    "function": (
        "def SPEC():\n    raise KeyError('gravity')\n",
        "SPEC() raised KeyError: 'gravity'",
    ),
    "gym_id": (
        "import envs\nfrom tests.custom_envs import pendulum\nfrom envs import Group, ObsLayout\n"
        "L = ObsLayout(obs_dim=3, groups=(Group('pole', 'SO2_cossin', (0, 1)),), velocities=(2,))\n"
        "SPEC = envs.custom_spec('p', 'Pendulm-v1', L, lambda o, a, n: o[..., 0])\n",
        "p: gymnasium cannot make 'Pendulm-v1'",
    ),
    "cos_sin_swapped": (  # the reward reads the observation itself, right; only the layout has cos and sin swapped
        "import envs\nfrom tests.custom_envs import pendulum_reward\nfrom envs import Group, ObsLayout\n"
        "L = ObsLayout(obs_dim=3, groups=(Group('pole', 'SO2_cossin', (1, 0)),), velocities=(2,))\n"
        "SPEC = envs.custom_spec('p', 'Pendulum-v1', L, pendulum_reward)\n",
        "p: group 'pole' (SO2_cossin) reads its angle the wrong way round",
    ),
    "returns_none": ("def SPEC():\n    return None\n", "SPEC() returned a NoneType, not an envs.EnvSpec"),
    "episode_length": (  # accepted before, then a traceback once the run reached its first episode
        "import envs\nfrom tests.custom_envs import pendulum_reward\nfrom envs import Group, ObsLayout\n"
        "L = ObsLayout(obs_dim=3, groups=(Group('pole', 'SO2_cossin', (0, 1)),), velocities=(2,))\n"
        "SPEC = envs.custom_spec('p', 'Pendulum-v1', L, pendulum_reward, episode_length=-5)\n",
        "p: episode_length must be a positive int (or None: the env's), got -5",
    ),
    "act_dim": (
        "import dataclasses\nfrom tests.custom_envs import pendulum\n"
        "SPEC = dataclasses.replace(pendulum(), act_dim=2, action_low=(-2.0, -2.0), action_high=(2.0, 2.0))\n",
        "the spec says obs_dim 3 and act_dim 2, Pendulum-v1 has observations (3,) and actions (1,)",
    ),
}


@pytest.mark.parametrize("case", sorted(SPEC_ERRORS))
def test_a_spec_that_fails_is_one_line_and_exit_2(tmp_path, case):
    text, fragment = SPEC_ERRORS[case]
    me = _user_folder(tmp_path, bad=text)
    (me / "tests").symlink_to(ROOT / "tests")  # the examples build on tests/custom_envs.py
    line = _one_error(_command(["--env", "bad:SPEC", "--print-config"], me))
    assert fragment in line


def test_the_reward_is_checked_against_the_envs_on_real_transitions_and_on_a_large_batch():
    with pytest.raises(ValueError, match=r"reward_fn gives 123 where Pendulum-v1 gave .* reward_differs=True"):
        envs.custom_spec("p", "Pendulum-v1", LAYOUT, lambda o, a, n: torch.full(o.shape[:-1], 123.0))

    def swapped(obs, act, next_obs):  # cos and sin read the wrong way round
        return pendulum_reward(obs[..., [1, 0, 2]], act, next_obs)

    with pytest.raises(ValueError, match="check the layout"):
        envs.custom_spec("p", "Pendulum-v1", LAYOUT, swapped)
    shaped = envs.custom_spec("p", "Pendulum-v1", LAYOUT, swapped, reward_differs=True)  # on purpose: accepted
    assert shaped.name == "p"

    def small_batches_only(obs, act, next_obs):
        out = pendulum_reward(obs, act, next_obs)
        return out if out.shape[0] < 1000 else out[:1000]

    with pytest.raises(ValueError, match=r"got \(1000,\) for inputs of shape \(10000, 3\)"):
        envs.custom_spec("p", "Pendulum-v1", LAYOUT, small_batches_only)


def test_a_hand_built_spec_of_the_wrong_size_is_refused_at_registration():
    spec = envs.custom_spec("p", "Pendulum-v1", LAYOUT, pendulum_reward)
    wrong = dataclasses.replace(spec, name="p2", act_dim=2, action_low=(-2.0, -2.0), action_high=(2.0, 2.0))
    with pytest.raises(ValueError, match="act_dim 2"):
        envs.register(wrong)


@pytest.mark.parametrize("name", ["reacher", "inverteddoublependulum"])
def test_a_layout_with_cos_and_sin_swapped_is_refused_against_mujocos_own_joint_angles(name):
    """The catalogue's cos/sin layouts (checked by the GEM head's round trips) pass; each group swapped is refused,
    judged against MuJoCo's qpos on real transitions."""
    from envs.custom import _real_transitions, check_angles

    spec = envs.get(name)
    env = spec.make()
    probe = _real_transitions(env, env.action_space)
    env.close()
    check_angles(name, spec.layout, probe)
    for group in spec.layout.groups_of("SO2_cossin"):
        swapped = dataclasses.replace(group, indices=group.indices[::-1])
        layout = dataclasses.replace(
            spec.layout, groups=tuple(swapped if g == group else g for g in spec.layout.groups)
        )
        with pytest.raises(ValueError, match=re.escape(f"(cos_index, sin_index) are {group.indices}")):
            check_angles(name, layout, probe)
    group, (v, *rest) = spec.layout.groups_of("SO2_cossin")[0], spec.layout.velocities  # a velocity read as a cosine
    wrong = dataclasses.replace(group, indices=(v, group.indices[1]))
    groups = tuple(wrong if g == group else g for g in spec.layout.groups)
    layout = dataclasses.replace(spec.layout, groups=groups, velocities=(group.indices[0], *rest))
    with pytest.raises(ValueError, match="is not a cosine and a sine"):
        check_angles(name, layout, probe)


def _catalogue_functions(name: str) -> tuple[str, ObsLayout, object, object]:
    """A catalogue env as a user would write it: its gym id, layout and exact reward and termination."""
    spec = envs.get(name)
    return spec.gym_id, spec.layout, spec.reward_fn, spec.terminated_fn


def test_the_termination_is_checked_against_the_envs_until_the_episode_ends():
    """InvertedPendulum ends an episode when the pole tips past 0.2 rad (within a few random steps): a spec that
    leaves the termination out, or ends every step, is refused; its own exact termination, or a differing one said
    to differ on purpose, is taken."""
    gym_id, layout, reward, terminated = _catalogue_functions("invertedpendulum")
    kwargs = envs.get("invertedpendulum").env_kwargs
    assert envs.custom_spec("ip", gym_id, layout, reward, terminated, env_kwargs=kwargs).name == "ip"
    with pytest.raises(ValueError, match=r"no terminated_fn \(never terminates\) says the episode goes on where") as e:
        envs.custom_spec("ip", gym_id, layout, reward, env_kwargs=kwargs)
    assert "terminated_differs=True" in str(e.value) and "\n" not in str(e.value)

    def always(obs, act, next_obs):
        return torch.ones(obs.shape[:-1], dtype=torch.bool)

    with pytest.raises(ValueError, match=r"terminated_fn says the episode ends where .* went on .* \(step 0 "):
        envs.custom_spec("ip", gym_id, layout, reward, always, env_kwargs=kwargs)
    spec = envs.custom_spec("ip", gym_id, layout, reward, env_kwargs=kwargs, terminated_differs=True)
    assert not spec.terminated_fn(torch.zeros(2, 4), torch.zeros(2, 1), torch.zeros(2, 4)).any()

    def float32_only(obs, act, next_obs):  # works on the planner's float32, not on the checks' float64
        return ((next_obs @ torch.ones(4)).abs() > 1e9) | terminated(obs, act, next_obs)

    with pytest.raises(ValueError, match=r"terminated_fn raised RuntimeError on real transitions in float64") as e:
        envs.custom_spec("ip", gym_id, layout, reward, float32_only, env_kwargs=kwargs)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("name", envs.names())
def test_every_catalogue_layout_passes_the_angle_and_velocity_checks_against_mujoco(name):
    """The catalogue's layouts (checked against MuJoCo's joints in tests/test_envs.py) are what the checks accept."""
    from envs.custom import _real_transitions, check_angles

    spec = envs.get(name)
    env = spec.make()
    probe = _real_transitions(env, env.action_space)
    env.close()
    check_angles(name, spec.layout, probe)


def test_a_layout_with_an_angle_and_a_velocity_swapped_is_refused_against_mujocos_qpos_and_qvel():
    """InvertedPendulum's observation is (cart, hinge angle, cart velocity, hinge velocity): a layout that reads the
    hinge angle from entry 2 and the velocities from entries 0-1 keeps the reward right (it reads obs directly) but
    would have GEM wrap a velocity; qpos and qvel show the swap."""
    gym_id, layout, reward, terminated = _catalogue_functions("invertedpendulum")
    kwargs = envs.get("invertedpendulum").env_kwargs
    swapped = ObsLayout(obs_dim=4, groups=(Group("cart", "Rn", (3,)), Group("hinge", "SO2_angle", (2,))),
                        velocities=(0, 1))  # fmt: skip
    with pytest.raises(
        ValueError, match=r"group 'hinge' \(SO2_angle\) reads entry 2, which is the simulator's velocity"
    ):
        envs.custom_spec("ip", gym_id, swapped, reward, terminated, env_kwargs=kwargs)
    angle_as_velocity = ObsLayout(obs_dim=4, groups=(Group("cart", "Rn", (0, 2)),), velocities=(1, 3))
    with pytest.raises(ValueError, match=r"velocities include entry 1, which is the simulator's position qpos\[1\]"):
        envs.custom_spec("ip", gym_id, angle_as_velocity, reward, terminated, env_kwargs=kwargs)


FAILING_MODULE = """
import gymnasium
import numpy as np

import envs
from envs import Group, ObsLayout
from mypend import pendulum_reward

MODE, AFTER = {mode!r}, {after}
READY = False  # the spec's checks step it too: it fails only in the run


class Failing(gymnasium.Wrapper):
    def __init__(self, env):
        super().__init__(env)
        self.steps = 0

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps += 1
        if READY and self.steps > AFTER:
            if MODE == "raise":
                raise RuntimeError("simulator blew up")
            obs = {{"nan": obs * np.nan, "shape": np.concatenate([obs, obs])}}.get(MODE, obs)
            reward = float("inf") if MODE == "reward" else reward
        return obs, reward, terminated, truncated, info


gymnasium.register("Failing-v0", entry_point=lambda **kw: Failing(gymnasium.make("Pendulum-v1", **kw).unwrapped))
LAYOUT = ObsLayout(obs_dim=3, groups=(Group("pole", "SO2_cossin", (0, 1)),), velocities=(2,))
SPEC = envs.custom_spec("failing", "Failing-v0", LAYOUT, pendulum_reward, episode_length=200)
READY = True
"""
SEED_STEPS = "the random steps before trial 0 (seed_steps): the env's step 11 of the episode"


@pytest.mark.parametrize(
    "mode, after, said",
    [
        ("raise", 60, "trial 0: the env's step 11 of the episode raised RuntimeError: simulator blew up"),
        ("nan", 30, f"{SEED_STEPS} returned a non-finite observation (nan or inf)"),
        ("shape", 30, f"{SEED_STEPS} returned an observation of shape (6,), its reset one of (3,)"),
        ("reward", 30, f"{SEED_STEPS} returned a non-finite reward (inf)"),
    ],
)
def test_your_env_that_fails_during_the_run_is_one_line_and_exit_3(tmp_path, mode, after, said):
    """Your env's step raising, or returning an observation of another shape, mid-run, was a traceback (exit 1); a
    nan observation became "the dynamics model predicts non-finite states" (and a replay buffer the resume refuses as
    damaged), a nan or inf reward a run that ended "done" with a nan episode reward, which pets.compare counts as a
    diverged run. Each is now one line naming the step, exit 3, and not recorded as the model's divergence."""
    me = _user_folder(tmp_path, failing=FAILING_MODULE.format(mode=mode, after=after))
    run = me / "run"
    proc = _command(
        ["--env", "failing:SPEC", "--model", "delta", "--trials", "1", "--out", "run", "--quiet", *SMALL], me
    )
    lines = [line for line in proc.stderr.splitlines() if line.strip() and not line.startswith("run directory:")]
    assert proc.returncode == 3 and "Traceback" not in proc.stderr, proc.stderr
    assert len(lines) == 1 and lines[0].startswith(f"run_pets.py: error: {said}; "), lines
    assert (run / "config.yaml").is_file() and not (run / "diverged.txt").exists()


ORACLE_MODULE = """
import gymnasium

import envs
import failing  # FAILING_MODULE's wrapper, here around a MuJoCo env

failing.READY = False  # the spec's checks step it too: it fails only in the episode
gymnasium.register("FailingIP-v0", entry_point=lambda **kw: failing.Failing(gymnasium.make("InvertedPendulum-v5")))
IP = envs.get("invertedpendulum")
SPEC = envs.custom_spec("failing_ip", "FailingIP-v0", IP.layout, IP.reward_fn, IP.terminated_fn, episode_length=50)
failing.READY = True
"""
ORACLE_SMALL = ["--steps", "10", "--episodes", "1", "planner.population=8", "planner.horizon=3", "threads=1"]


def test_the_oracle_refuses_your_env_of_another_simulator_in_one_line(tmp_path):
    """pets.oracle sets a copy of MuJoCo to the live env's state; a Pendulum (not MuJoCo) was an AttributeError
    traceback at its first planning step."""
    me = _user_folder(tmp_path, failing=FAILING_MODULE.format(mode="raise", after=1000))
    proc = _command(["pets.oracle", "--env", "failing:SPEC", *ORACLE_SMALL], me, module=True)
    assert _one_error(proc) == (
        "pets.oracle: error: the env PendulumEnv is not a MuJoCo env (no data.qpos and set_state): pets.oracle scores "
        "each candidate on a copy of the simulator set to the live env's state"
    )


def test_the_oracle_on_your_env_that_fails_mid_episode_is_one_line_and_exit_3(tmp_path):
    """Your MuJoCo env's step raising mid-episode under pets.oracle: one line naming the episode and step, exit 3."""
    me = _user_folder(tmp_path, failing=FAILING_MODULE.format(mode="raise", after=3), failing_ip=ORACLE_MODULE)
    proc = _command(["pets.oracle", "--env", "failing_ip:SPEC", *ORACLE_SMALL], me, module=True)
    errors = [line for line in proc.stderr.splitlines() if "error" in line]
    assert proc.returncode == 3 and "Traceback" not in proc.stderr, proc.stderr
    assert errors == [
        "pets.oracle: error: episode 0: the env's step 4 of the episode raised RuntimeError: simulator blew up"
    ]
