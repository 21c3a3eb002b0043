"""pets.oracle: the planner's objective scored by MuJoCo itself, checked against the real env."""

import json

import numpy as np
import pytest
import torch

import envs
from pets import oracle


def _stepped_return(env, actions: np.ndarray) -> float:
    """The real env's summed reward for ``actions`` from its current state, up to a termination."""
    total = 0.0
    for action in actions:
        _, reward, terminated, _, _ = env.step(action)
        total += reward
        if terminated:
            break
    return total


@pytest.mark.parametrize("name", ["inverteddoublependulum", "hopper"])
def test_returns_equal_the_real_env_stepped_through_each_sequence_and_leave_it_untouched(name: str) -> None:
    spec = envs.get(name)
    env = spec.make()
    env.reset(seed=3)
    for _ in range(2):  # away from the reset state
        env.step(np.zeros(spec.act_dim))
    qpos, qvel = env.unwrapped.data.qpos.copy(), env.unwrapped.data.qvel.copy()
    rng = np.random.default_rng(0)
    actions = rng.uniform(spec.action_low, spec.action_high, size=(4, 30, spec.act_dim))
    returns = oracle.SimulatorEvaluator(env, spec.make)(torch.zeros(spec.obs_dim), torch.as_tensor(actions))

    np.testing.assert_array_equal(env.unwrapped.data.qpos, qpos)  # the live env is not touched
    np.testing.assert_array_equal(env.unwrapped.data.qvel, qvel)
    expected = []
    for sequence in actions:  # the same sequences through a copy of the live env, one at a time
        real = spec.make()
        real.reset(seed=0)
        real.unwrapped.set_state(qpos, qvel)
        expected.append(_stepped_return(real.unwrapped, sequence))
    np.testing.assert_allclose(returns.numpy(), expected, rtol=1e-12)
    assert returns.dtype == torch.float64 and len(set(returns.tolist())) == 4


def test_termination_penalty_is_subtracted_where_the_real_env_terminates() -> None:
    """Hopper for 60 steps, half the sequences idle, half full random torques: those that fall lose the penalty."""
    spec = envs.get("hopper")
    env = spec.make()
    env.reset(seed=3)
    scale = np.array([0.0] * 4 + [1.0] * 4).reshape(8, 1, 1)
    actions = torch.as_tensor(scale * np.random.default_rng(1).uniform(-1, 1, size=(8, 60, spec.act_dim)))
    plain = oracle.SimulatorEvaluator(env, spec.make)(torch.zeros(spec.obs_dim), actions)
    penalised = oracle.SimulatorEvaluator(env, spec.make, termination_penalty=100.0)(torch.zeros(spec.obs_dim), actions)
    fell = []
    for sequence in actions.numpy():
        real = spec.make()
        real.reset(seed=3)
        terminated = False
        for action in sequence:
            terminated = real.step(action)[2]
            if terminated:
                break
        fell.append(terminated)
    assert 0 < sum(fell) < len(fell)  # both kinds among the sequences
    np.testing.assert_allclose((plain - penalised).numpy(), [100.0 if f else 0.0 for f in fell], atol=1e-9)


def test_mpc_with_the_true_dynamics_balances_the_pendulum(tmp_path) -> None:
    """InvertedPendulum at the fast preset's planner: the pole stays up for the whole (shortened) episode."""
    out = tmp_path / "oracle.json"
    argv = ["--env", "invertedpendulum", "--preset", "fast", "--steps", "40", "--json", str(out), "--quiet"]
    code = oracle.main(argv)
    assert code == 0
    (episode,) = json.loads(out.read_text())["episodes"]
    assert episode["steps"] == 40 and not episode["terminated"] and episode["reward"] == 40.0
    assert episode["max_abs_cart_x"] < 1.0


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--env", "nope"], "unknown env 'nope'"),
        (["--env", "reacher", "--steps", "0"], "--steps must be >= 1"),
        (["--env", "reacher", "planner.horizon=0"], "planner.horizon must be >= 1"),
    ],
)
def test_bad_input_exits_2_with_a_clear_message(argv, message, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        oracle.main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
