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
    transitions, positions = _real_transitions(env, env.action_space)
    env.close()
    check_angles(name, spec.layout, transitions, positions)
    for group in spec.layout.groups_of("SO2_cossin"):
        swapped = dataclasses.replace(group, indices=group.indices[::-1])
        layout = dataclasses.replace(
            spec.layout, groups=tuple(swapped if g == group else g for g in spec.layout.groups)
        )
        with pytest.raises(ValueError, match=re.escape(f"(cos_index, sin_index) are {group.indices}")):
            check_angles(name, layout, transitions, positions)
    group, (v, *rest) = spec.layout.groups_of("SO2_cossin")[0], spec.layout.velocities  # a velocity read as a cosine
    wrong = dataclasses.replace(group, indices=(v, group.indices[1]))
    groups = tuple(wrong if g == group else g for g in spec.layout.groups)
    layout = dataclasses.replace(spec.layout, groups=groups, velocities=(group.indices[0], *rest))
    with pytest.raises(ValueError, match="is not a cosine and a sine"):
        check_angles(name, layout, transitions, positions)
