"""The learned terminal value (pets/planning/value.py): its targets against scipy, its fit, the planner's use of it,
and a run with it (checkpointed, resumed to the same metrics)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.signal import lfilter

import envs
from dynamics.model import DynamicsModel
from pets import builder
from pets.config import ConfigError, make_config
from pets.data.collect import AgentPolicy
from pets.data.rollout import RandomPolicy, run_steps
from pets.planning.propagation import PROPAGATIONS, TrajectoryEvaluator
from pets.planning.value import ValueFunction, episode_ends, returns_to_go
from tests.test_cli import TINY, cli, rows
from tests.test_propagation import OBS_DIM, FakeEnsemble, first_action_terminates, make_head, unit_reward
from tests.tiny import replacing


def discounted_cumsum(x: np.ndarray, discount: float) -> np.ndarray:
    """scipy's filter form of ``y_t = x_t + discount * y_{t+1}`` (the usual RL idiom), as ground truth."""
    return lfilter([1.0], [1.0, -discount], x[::-1])[::-1]


def test_returns_to_go_match_scipy_per_episode() -> None:
    rng = np.random.default_rng(0)
    lengths = [5, 1, 12, 7]
    rewards = rng.normal(size=sum(lengths))
    bootstrap_after = [0.0, 3.5, 0.0, -2.0]  # value after each episode's last step (0: terminated)
    ends, boot = np.zeros(len(rewards), bool), np.zeros(len(rewards))
    want, start = [], 0
    for length, b in zip(lengths, bootstrap_after):
        seg = rewards[start : start + length].copy()
        seg[-1] += 0.97 * b  # the bootstrapped tail enters through the last reward
        want.append(discounted_cumsum(seg, 0.97))
        ends[start + length - 1], boot[start + length - 1] = True, b
        start += length
    got = returns_to_go(torch.tensor(rewards), torch.tensor(ends), torch.tensor(boot), 0.97)
    np.testing.assert_allclose(got.numpy(), np.concatenate(want), rtol=1e-12)


def test_episode_ends_finds_the_boundaries_of_real_episodes() -> None:
    """Random-action InvertedPendulum episodes put back to back, as the replay buffer holds them."""
    spec = envs.get("invertedpendulum")
    env = spec.make()
    episodes = run_steps(
        env,
        RandomPolicy(spec.action_low, spec.action_high),
        200,
        max_steps=1000,
        reset_seeds=iter(range(100)),
        rng=np.random.default_rng(0),
    )
    env.close()
    assert len(episodes) > 3
    obs = torch.tensor(np.concatenate([e.obs for e in episodes]), dtype=torch.float32)
    nxt = torch.tensor(np.concatenate([e.next_obs for e in episodes]), dtype=torch.float32)
    want = np.cumsum([len(e) for e in episodes]) - 1
    assert torch.nonzero(episode_ends(obs, nxt)).flatten().tolist() == want.tolist()


def test_value_function_is_zero_until_fitted_then_fits_a_smooth_target() -> None:
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(2000, 3, generator=g) * torch.tensor([1.0, 5.0, 0.1])
    target = 50.0 - 10.0 * obs[:, 0].square() + obs[:, 1]
    v = ValueFunction(3, hidden_size=64, discount=0.99)
    assert torch.equal(v(obs), torch.zeros(2000))
    mse = v.fit(obs, target, g, steps=1500)
    assert mse < 0.02 * float(target.var()), (mse, float(target.var()))
    with pytest.raises(ValueError, match="discount"):
        ValueFunction(3, discount=1.0)


@pytest.mark.parametrize("prop", PROPAGATIONS)
def test_terminal_value_is_added_for_surviving_rows_only(prop: str) -> None:
    """Unit rewards, termination when the action's first entry > 0.5 (one step only), V(obs) = 100 + obs_0:
    a candidate that terminates gets its steps only; one that survives also V of its final state."""
    ens = FakeEnsemble(torch.full((3, OBS_DIM), 0.5))  # every member moves each coordinate by +0.5 per step
    h, term = 6, first_action_terminates
    actions = torch.zeros(3, h, 2)
    actions[0, 2, 0] = 1.0  # terminates at step 2
    ev = TrajectoryEvaluator(
        DynamicsModel(make_head(), ens),
        unit_reward,
        term,
        particles=2,
        propagation=prop,
        terminal_value=lambda obs: 100.0 + obs[..., 0],
    )
    ret = ev(torch.zeros(OBS_DIM), actions, torch.Generator().manual_seed(0))
    torch.testing.assert_close(ret, torch.tensor([3.0, h + 100.0 + 0.5 * h, h + 100.0 + 0.5 * h]))


def test_config_checks_the_discount() -> None:
    with pytest.raises(ConfigError, match=r"value.discount must be in \(0, 1\)"):
        make_config("invertedpendulum", overrides={"value.discount": "1.0"})


def test_run_with_value_resumes_to_the_same_metrics(tmp_path) -> None:
    """The value's weights and generator are in the checkpoint: 1 trial + resume to 3 = 3 trials in one go."""
    args = ["--env", "invertedpendulum", "--seed", 3, *replacing(TINY, "value.steps=50"), "value.enabled=true"]
    cli(*args, "--trials", 3, "--out", tmp_path / "ref")
    cli(*args, "--trials", 1, "--out", tmp_path / "split")
    cli("--resume", tmp_path / "split", "--trials", 3)
    got, want = rows(tmp_path / "split"), rows(tmp_path / "ref")
    assert [r["episode_reward"] for r in got] == [r["episode_reward"] for r in want]
    state = torch.load(tmp_path / "ref" / "checkpoint.pt", map_location="cpu", weights_only=False)  # run on cuda too
    assert bool(state["value"]["fitted"])
    # The run's agent for pets.collect --policy run:DIR plans with the run's value, not a fresh one.
    policy = AgentPolicy(tmp_path / "ref", device="cpu")
    value = policy.agent.evaluator.terminal_value
    obs = torch.as_tensor(state["buffer"]["obs"][:50])
    assert value is not None and torch.equal(value.net[0].weight, state["value"]["net.0.weight"])
    assert value(obs).abs().max() > 0  # fitted: not the zero of an unfitted value
    cfg, spec, _ = builder.load_model(tmp_path / "ref")
    cfg.value.enabled = False
    assert builder.load_value(tmp_path / "ref", cfg, spec) is None
