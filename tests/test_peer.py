"""docs/scripts/peer_mbrl.py (issue 36): importable and refusing in one line without mbrl-lib; its own pieces
that need no mbrl-lib (observation conversion, trial wrapper, paired summary) on real data."""

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from tests import warm

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "docs" / "scripts" / "peer_mbrl.py"
MBRL_HERE = importlib.util.find_spec("mbrl") is not None


def load_script():
    spec = importlib.util.spec_from_file_location("peer_mbrl", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_imports_without_mbrl():
    peer = load_script()
    assert "mbrl" not in sys.modules or MBRL_HERE  # importing the script does not import mbrl-lib
    parser = peer.build_parser()
    assert parser.parse_args(["plan"]).repeats == 7
    assert parser.parse_args(["learn", "--env", "reacher"]).seeds == "0,1,2,3,4"


@pytest.mark.skipif(MBRL_HERE, reason="mbrl-lib is importable in this environment: nothing to refuse")
@pytest.mark.parametrize("command", [["plan"], ["learn", "--env", "invertedpendulum"]])
def test_refuses_in_one_line_without_mbrl(command):
    out = warm.run([sys.executable, str(SCRIPT), *command], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 2
    assert out.stdout == ""
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert lines[0].startswith("peer_mbrl.py: mbrl-lib (mbrl 0.2.0) is not importable")
    assert "docs/scripts/peer_mbrl.py setup VENV" in lines[0]


@pytest.mark.skipif(MBRL_HERE, reason="mbrl-lib is importable in this environment")
def test_require_mbrl_raises_with_hint():
    peer = load_script()
    with pytest.raises(peer.MbrlMissing, match="setup VENV"):
        peer.require_mbrl()


def test_halfcheetah_conversion_matches_the_v5_reward():
    """mbrl's observation (x velocity first) turns mbrl's own reward formula (next_obs[0] - 0.1 |a|^2) into
    gymnasium HalfCheetah-v5's reward of the same transitions."""
    import envs

    peer = load_script()
    spec = envs.get("halfcheetah")
    env = spec.make()
    rng = np.random.default_rng(3)
    obs, act, nxt, rew = [], [], [], []
    o, _ = env.reset(seed=3)
    for _ in range(30):
        a = rng.uniform(-1, 1, 6)
        n, r, *_ = env.step(a)
        for store, x in ((obs, o), (act, a), (nxt, n), (rew, r)):
            store.append(x)
        o = n
    env.close()
    obs, act, nxt = (np.asarray(x, dtype=np.float64) for x in (obs, act, nxt))
    obs_m, act_m, nxt_m = peer.halfcheetah_mbrl_data(obs, act, nxt, spec.dt)
    mbrl_reward = nxt_m[:, 0] - 0.1 * np.square(act_m).sum(1)  # mbrl.env.reward_fns.halfcheetah
    np.testing.assert_allclose(mbrl_reward, rew, rtol=1e-4, atol=1e-4)
    assert obs_m[0, 0] == 0.0  # a reset: mbrl's env starts with prev_qpos = qpos
    np.testing.assert_array_equal(obs_m[1:], nxt_m[:-1])  # one episode: each obs is the previous next obs
    np.testing.assert_array_equal(obs_m[:, 1:], obs[:, 1:].astype(np.float32))


def test_trial_wrapper_seeds_times_and_stops():
    import gymnasium

    import envs
    from pets.loop import SEED_PHASE, episode_reset_seed

    peer = load_script()
    spec = envs.get("reacher")  # never terminates: the episode lengths below are the ones asked for
    env = peer.trial_wrapper(gymnasium.wrappers.TimeLimit(spec.make(), 20), seed=4, trials=2, seed_steps=30)
    ref = spec.make()
    starts = []
    for phase_index in range(4):  # seed phase: 30 steps over two episodes (20 + 10), then two trials
        obs, _ = env.reset()
        starts.append(obs)
        for _ in range(20 if phase_index != 1 else 10):
            *_, term, trunc, _ = env.step(np.zeros(2))
            if term or trunc:
                break
    with pytest.raises(peer.TrialsDone):
        env.reset()
    phases = [e["phase"] for e in env.episodes]
    assert phases == ["seed", "seed", "trial", "trial"]
    for got, index in zip(starts, [SEED_PHASE, SEED_PHASE + 1, 0, 1]):
        want, _ = ref.reset(seed=episode_reset_seed(4, index))
        np.testing.assert_array_equal(got, want)
    assert all(e["wall_s"] >= 0 and e["cpu_s"] >= 0 and e["length"] > 0 for e in env.episodes)
    assert env.episodes[-1]["env_steps"] == env.steps


def test_learning_summary_pairs_and_tests():
    peer = load_script()
    rows = []
    for seed in range(5):
        for impl, base in (("gem-pets", 10.0 + seed), ("mbrl-lib", 8.0 + seed)):
            for trial in range(4):
                rows.append(
                    {
                        "impl": impl,
                        "seed": seed,
                        "trial": trial,
                        "episode_reward": base + trial,
                        "trial_wall_s": 1.0,
                        "run_cpu_s": 8.0 if impl == "gem-pets" else 16.0,
                        "env_steps": 100 * (trial + 1),
                        "steps_to_threshold": 300.0 if impl == "gem-pets" or seed < 2 else math.nan,
                    }
                )
    summary = {s["metric"]: s for s in peer.learning_summary(rows, trials=4)}
    final = summary["final_reward_last3"]
    assert final["n_pairs"] == 5
    assert final["diff_mean"] == pytest.approx(2.0)
    assert final["diff_ci_low"] == final["diff_ci_high"] == pytest.approx(2.0)  # every pair differs by 2
    assert final["sign_flip_p"] == pytest.approx(2 / 32)  # the smallest p five pairs can reach
    cpu = summary["cpu_s_per_trial"]
    assert cpu["gem_pets_mean"] == 2.0 and cpu["mbrl_lib_mean"] == 4.0
    assert math.isclose(cpu["diff_mean"], -2.0)
    assert summary["cpu_s_per_env_step"]["diff_mean"] == pytest.approx(8 / 400 - 16 / 400)
    reached = summary["reached_threshold"]
    assert reached["gem_pets_mean"] == 1.0 and reached["mbrl_lib_mean"] == pytest.approx(0.4)
    assert summary["steps_to_threshold"]["n_pairs"] == 2  # only the seeds where both reached it


def test_the_online_halfcheetah_wrapper_gives_mbrls_observations_and_the_true_rewards():
    """mbrl-lib's learning loop sees HalfCheetah-v5 through the wrapper: its observations are those of the offline
    conversion checked above (x velocity first, 0 at a reset), over a reset inside the rollout too, and the
    rewards are the env's own."""
    import envs

    peer = load_script()
    spec = envs.get("halfcheetah")
    raw, wrapped = spec.make(), peer.halfcheetah_velocity_obs(spec.make(), spec.dt)
    rng = np.random.default_rng(5)
    obs, act, nxt, seen, rewards = [], [], [], [], []
    for episode in range(2):
        o, _ = raw.reset(seed=episode)
        w, _ = wrapped.reset(seed=episode)
        first = w
        for _ in range(15):
            a = rng.uniform(-1, 1, 6)
            n, r, *_ = raw.step(a)
            wn, wr, *_ = wrapped.step(a)
            obs.append(o), act.append(a), nxt.append(n), seen.append(wn), rewards.append((r, wr))
            o = n
        assert first[0] == 0.0
    obs_m, _, nxt_m = peer.halfcheetah_mbrl_data(*(np.asarray(x, dtype=np.float64) for x in (obs, act, nxt)), spec.dt)
    np.testing.assert_allclose(np.asarray(seen), nxt_m, rtol=1e-5, atol=1e-5)
    assert all(r == wr for r, wr in rewards)
