"""pets.data.rollout: run_episode against stepping a real env by hand, its stopping rules, the hook and run_steps."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import envs
from pets.data.rollout import Episode, MPCPolicy, RandomPolicy, run_episode, run_steps


def _by_hand(spec: envs.EnvSpec, seed: int, actions: np.ndarray, limit: int | None = None) -> dict[str, list]:
    """Step ``spec.make()`` with ``actions`` until it ends (or ``limit`` steps); the raw results."""
    env = spec.make()
    obs, _ = env.reset(seed=seed)
    rec: dict[str, list] = {k: [] for k in ("obs", "next_obs", "rewards", "terminated", "truncated")}
    for action in actions[:limit]:
        nxt, reward, term, trunc, _ = env.step(action)
        for k, v in zip(rec, (obs, nxt, float(reward), term, trunc)):
            rec[k].append(v)
        obs = nxt
        if term or trunc:
            break
    env.close()
    return rec


def _uniform(spec: envs.EnvSpec, seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.array([rng.uniform(spec.action_low, spec.action_high) for _ in range(n)])


def test_random_policy_draws_as_generator_uniform() -> None:
    """The PETS loop's seed steps drew ``rng.uniform(action_low, action_high)``; the policy draws the same."""
    spec = envs.get("hopper")
    policy, rng = RandomPolicy(spec.action_low, spec.action_high), np.random.default_rng(7)
    policy.reset(rng)
    drawn = np.array([policy.act(np.zeros(spec.obs_dim)) for _ in range(5)])
    np.testing.assert_array_equal(drawn, _uniform(spec, 7, 5))
    assert drawn.dtype == np.float64


def test_episode_matches_stepping_by_hand_until_termination() -> None:
    """Invertedpendulum under random actions falls within a few steps: the episode ends at the termination."""
    spec = envs.get("invertedpendulum")
    env = spec.make()
    episode = run_episode(
        env, RandomPolicy(spec.action_low, spec.action_high), max_steps=200, reset_seed=3, rng=np.random.default_rng(5)
    )
    env.close()
    rec = _by_hand(spec, 3, _uniform(spec, 5, 200))
    n = len(rec["rewards"])
    assert 1 <= n < 200 and len(episode) == n
    assert rec["terminated"][-1] and episode.terminated[-1] and not episode.terminated[:-1].any()
    assert episode.done and not episode.truncated.any()
    np.testing.assert_array_equal(episode.act, _uniform(spec, 5, n))
    np.testing.assert_array_equal(episode.obs, np.array(rec["obs"]))
    np.testing.assert_array_equal(episode.next_obs, np.array(rec["next_obs"]))
    np.testing.assert_array_equal(episode.rewards, rec["rewards"])
    np.testing.assert_array_equal(episode.states, np.array(rec["obs"] + rec["next_obs"][-1:]))
    assert episode.total_reward == sum(rec["rewards"])


def test_max_steps_truncates_and_the_env_time_limit_too() -> None:
    spec = envs.get("reacher")  # never terminates
    actions = _uniform(spec, 1, 12)
    env = spec.make()
    policy = RandomPolicy(spec.action_low, spec.action_high)
    episode = run_episode(env, policy, max_steps=12, reset_seed=0, rng=np.random.default_rng(1))
    rec = _by_hand(spec, 0, actions, limit=12)
    assert len(episode) == 12 and episode.done
    assert episode.truncated.tolist() == [False] * 11 + [True] and not episode.terminated.any()
    np.testing.assert_array_equal(episode.next_obs, np.array(rec["next_obs"]))
    np.testing.assert_array_equal(episode.rewards, rec["rewards"])
    env.close()
    short = spec.make(max_episode_steps=5)  # the env's own time limit ends it first
    episode = run_episode(short, policy, max_steps=12, reset_seed=0, rng=np.random.default_rng(1))
    short.close()
    assert len(episode) == 5 and episode.truncated[-1]
    np.testing.assert_array_equal(episode.rewards, rec["rewards"][:5])


def test_on_step_sees_the_episode_so_far() -> None:
    spec = envs.get("reacher")
    env = spec.make()
    seen: list[tuple[int, float, bool, np.ndarray]] = []

    def hook(so_far: Episode) -> None:
        seen.append((len(so_far), so_far.total_reward, so_far.done, so_far.next_obs[-1].copy()))

    policy = RandomPolicy(spec.action_low, spec.action_high)
    episode = run_episode(env, policy, max_steps=6, reset_seed=2, rng=np.random.default_rng(0), on_step=hook)
    env.close()
    assert [s[0] for s in seen] == [1, 2, 3, 4, 5, 6]
    assert [s[2] for s in seen] == [False] * 5 + [True]
    assert [s[1] for s in seen] == list(itertools.accumulate(episode.rewards.tolist()))
    np.testing.assert_array_equal(np.array([s[3] for s in seen]), episode.next_obs)


def test_mpc_policy_resets_the_agent_and_times_it() -> None:
    class Agent:
        resets = 0

        def reset(self) -> None:
            self.resets += 1

        def act(self, obs: np.ndarray) -> np.ndarray:
            return np.zeros(2)

    agent = Agent()
    policy = MPCPolicy(agent)
    env = envs.get("reacher").make()
    episode = run_episode(env, policy, max_steps=4, reset_seed=0)
    env.close()
    assert agent.resets == 1 and len(episode) == 4 and policy.seconds > 0.0
    np.testing.assert_array_equal(episode.act, np.zeros((4, 2)))


def test_run_steps_cuts_the_last_episode_and_shares_the_generator() -> None:
    spec = envs.get("invertedpendulum")
    env = spec.make()
    episodes = run_steps(
        env,
        RandomPolicy(spec.action_low, spec.action_high),
        30,
        max_steps=200,
        reset_seeds=itertools.count(10),
        rng=np.random.default_rng(4),
    )
    env.close()
    assert sum(len(e) for e in episodes) == 30 and len(episodes) > 1
    assert all(e.terminated[-1] for e in episodes[:-1])
    np.testing.assert_array_equal(np.concatenate([e.act for e in episodes]), _uniform(spec, 4, 30))
    first = _by_hand(spec, 10, _uniform(spec, 4, 30))
    np.testing.assert_array_equal(episodes[0].rewards, first["rewards"])


def test_max_steps_must_be_positive() -> None:
    env = envs.get("reacher").make()
    with pytest.raises(ValueError, match="max_steps"):
        run_episode(env, RandomPolicy([-1, -1], [1, 1]), max_steps=0)
    env.close()
