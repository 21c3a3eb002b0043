"""InvertedDoublePendulum with the true dynamics and linear-feedback candidates (docs/planning.md, 2026-11-23).

    python docs/scripts/idp_feedback_oracle.py HORIZON POPULATION ITERATIONS STEPS SEED GAIN_STD U_STD

Every MPC step, CEM (10 % elites, mean and std smoothed with alpha 0.1, the gains' std reset to GAIN_STD and
their mean warm-started) searches gains ``K`` of ``a = clip(u_t + K z(s), -1, 1)``, ``z`` = (cart x, sin 1,
sin 2, cart v, omega 1, omega 2) divided by (0.5, 0.2, 0.2, 1, 2, 2), plus an open-loop ``u`` of std U_STD (0:
none). Each candidate is scored by MuJoCo in closed loop over HORIZON steps from the live state. A one-off
experiment (numpy, a Python loop per candidate), not part of the package. On 2026-11-23:
``60 100 3 1000 0 1.0 0.0`` gave 1000 steps, reward 9358 (693 s on one Zen 4 core).
"""

import sys
import time

import gymnasium as gym
import numpy as np

H, pop, iters, steps, seed = (int(a) for a in sys.argv[1:6])
gain_std, u_std = float(sys.argv[6]), float(sys.argv[7])
rng = np.random.default_rng(seed)
env = gym.make("InvertedDoublePendulum-v5")
sim = gym.make("InvertedDoublePendulum-v5").unwrapped
sim.reset(seed=0)
obs, _ = env.reset(seed=seed)
IDX, SCALE = [0, 1, 2, 5, 6, 7], np.array([0.5, 0.2, 0.2, 1.0, 2.0, 2.0])


def features(o: np.ndarray) -> np.ndarray:
    return o[IDX] / SCALE


def closed_loop_return(K: np.ndarray, u: np.ndarray) -> float:
    sim.set_state(env.unwrapped.data.qpos.copy(), env.unwrapped.data.qvel.copy())
    o, total = env.unwrapped._get_obs(), 0.0
    for t in range(H):
        o, r, terminated, _, _ = sim.step(np.array([np.clip(u[t] + K @ features(o), -1, 1)]))
        total += r
        if terminated:
            break
    return total


mean_K, mean_u, total, xs, start = np.zeros(6), np.zeros(H), 0.0, [], time.time()
while len(xs) < steps:
    std_K, std_u = np.full(6, gain_std), np.full(H, u_std)
    for _ in range(iters):
        Ks = mean_K + std_K * rng.standard_normal((pop, 6))
        us = np.clip(mean_u + std_u * rng.standard_normal((pop, H)), -1, 1)
        values = np.array([closed_loop_return(k, u) for k, u in zip(Ks, us)])
        elite = np.argsort(values)[-pop // 10 :]
        mean_K, mean_u = 0.1 * mean_K + 0.9 * Ks[elite].mean(0), 0.1 * mean_u + 0.9 * us[elite].mean(0)
        std_K, std_u = Ks[elite].std(0) + 1e-3, us[elite].std(0) + 1e-3
    obs, r, terminated, truncated, _ = env.step(np.array([np.clip(mean_u[0] + mean_K @ features(obs), -1, 1)]))
    total += r
    xs.append(obs[0])
    mean_u = np.r_[mean_u[1:], mean_u[-1]]
    if terminated or truncated:
        break
print(
    f"horizon {H}, population {pop}, {iters} iterations, gain std {gain_std}, u std {u_std}, seed {seed}: "
    f"{len(xs)} steps, reward {total:.0f}, max |x| {np.abs(xs).max():.2f}, {time.time() - start:.0f} s"
)
