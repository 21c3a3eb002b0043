"""pets.oracle: the planner's objective scored by MuJoCo itself, checked against the real env."""

import json

import numpy as np
import pytest
import torch

import envs
from pets import oracle
from tests.test_cli import TINY, cli
from tests.tiny import replacing


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


def _hopper_sequences():
    """Hopper after a reset, 8 sequences of 60 steps (half idle, half full random torques) and, per sequence, the
    real env's last observation stepped through it and whether it fell."""
    spec = envs.get("hopper")
    env = spec.make()
    env.reset(seed=3)
    scale = np.array([0.0] * 4 + [1.0] * 4).reshape(8, 1, 1)
    actions = torch.as_tensor(scale * np.random.default_rng(1).uniform(-1, 1, size=(8, 60, spec.act_dim)))
    qpos, qvel = env.unwrapped.data.qpos.copy(), env.unwrapped.data.qvel.copy()
    fell, last = [], []
    for sequence in actions.numpy():
        real = spec.make().unwrapped
        real.reset(seed=0)
        real.set_state(qpos, qvel)
        for action in sequence:
            obs, _, terminated, _, _ = real.step(action)
            if terminated:
                break
        fell.append(terminated)
        last.append(obs)
    assert 0 < sum(fell) < len(fell)  # both kinds among the sequences
    return spec, env, actions, np.array(fell), np.array(last)


def test_termination_penalty_is_subtracted_where_the_real_env_terminates() -> None:
    """Those of the Hopper sequences that fall lose the penalty, the others nothing."""
    spec, env, actions, fell, _ = _hopper_sequences()
    plain = oracle.SimulatorEvaluator(env, spec.make)(torch.zeros(spec.obs_dim), actions)
    penalised = oracle.SimulatorEvaluator(env, spec.make, termination_penalty=100.0)(torch.zeros(spec.obs_dim), actions)
    np.testing.assert_allclose((plain - penalised).numpy(), np.where(fell, 100.0, 0.0), atol=1e-9)


def test_terminal_value_is_added_at_the_real_last_state_of_the_sequences_that_survive() -> None:
    """V(obs) = 10 x (torso height): added where the real env did not fall, at its real last observation."""
    spec, env, actions, fell, last = _hopper_sequences()
    plain = oracle.SimulatorEvaluator(env, spec.make)(torch.zeros(spec.obs_dim), actions)
    valued = oracle.SimulatorEvaluator(env, spec.make, terminal_value=lambda obs: 10.0 * obs[..., 0])(
        torch.zeros(spec.obs_dim), actions
    )
    expected = np.where(fell, 0.0, 10.0 * last[:, 0].astype(np.float32))
    np.testing.assert_allclose((valued - plain).numpy(), expected, rtol=1e-6, atol=1e-9)


def test_value_from_a_run_plans_with_that_runs_value(tmp_path) -> None:
    """--value-from RUN_DIR: the true dynamics with the terminal value a run learned; recorded in --json."""
    run = tmp_path / "run"
    tiny = replacing(TINY, "value.steps=50")
    cli("--env", "invertedpendulum", "--seed", 3, *tiny, "value.enabled=true", "--trials", 1, "--out", run)
    out = tmp_path / "oracle.json"
    argv = ["--env", "invertedpendulum", "--preset", "fast", "--steps", "20", "--json", str(out), "--quiet"]
    assert oracle.main([*argv, "--value-from", str(run)]) == 0
    record = json.loads(out.read_text())
    assert record["value_from"] == str(run) and record["episodes"][0]["steps"] == 20
    value = oracle._run_value(run, envs.get("invertedpendulum"))
    weights = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)["value"]["net.0.weight"]
    assert torch.equal(value.net[0].weight.cpu(), weights)


def test_value_from_refuses_what_holds_no_value_of_this_env(tmp_path, capsys) -> None:
    run = tmp_path / "run"
    cli("--env", "invertedpendulum", "--seed", 3, *TINY, "value.enabled=false", "--trials", 1, "--out", run)
    cases = [
        (["--env", "invertedpendulum", "--value-from", str(tmp_path)], "is not a run directory"),
        (["--env", "invertedpendulum", "--value-from", str(run)], "learned no terminal value"),
        (["--env", "hopper", "--value-from", str(run)], "is a run of invertedpendulum, not of hopper"),
    ]
    for argv, message in cases:
        with pytest.raises(SystemExit) as exc:
            oracle.main(argv)
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) <= 2, err  # the header line, then the error


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
        (
            ["--env", "reacher", "model.lr=5"],
            "the key model.lr is not read when planning with the true dynamics",
        ),
        (["--env", "reacher", "planner.population=10000000", "planner.horizon=100000"], "GB of host memory"),
    ],
)
def test_bad_input_exits_2_with_a_clear_message(argv, message, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        oracle.main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_the_memory_check_reads_the_hosts_memory_where_torch_sees_a_gpu(capsys, monkeypatch) -> None:
    """The oracle plans on the CPU: on a machine with a GPU (device auto is CUDA) its memory check read the GPU's
    free memory (seen on an H200, 2026-12-01). Here torch.cuda reports a GPU with no free memory."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda *device: (0, 141 * 1024**3))
    with pytest.raises(SystemExit) as exc:
        oracle.main(["--env", "reacher", "planner.population=10000000", "planner.horizon=100000"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "GB of host memory" in err, err
