"""Env catalogue against the real MuJoCo simulator (the ground truth).

Rewards and terminations are replayed on real transitions (random and smoothed-random actions,
several seeds, episodes run until they terminate, perturbed starts near Ant's termination), and
the layouts are checked entry by entry against MuJoCo's qpos/qvel/data.
"""

from __future__ import annotations

import functools

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.envs.mujoco.humanoid_v5 import mass_center

import envs
from envs.layout import Group, ObsLayout

NAMES = envs.names()
#: raw env steps replayed per env (Ant/Humanoid are ~4x slower per step).
STEPS = {"inverteddoublependulum": 5000, "ant": 500, "humanoid": 500}
DEFAULT_STEPS = 2000
CLIPPED_VEL = {"inverteddoublependulum", "hopper", "walker2d"}


PERTURBED = {"ant", "inverteddoublependulum"}


def _perturbed_start(name: str, env: gymnasium.Env, rng: np.random.Generator) -> np.ndarray:
    """Ant: torso thrown up or down, or tumbling (near termination); IDP: hinges spinning past the 10 rad/s clip."""
    u = env.unwrapped
    qpos, qvel = u.init_qpos.copy(), u.init_qvel.copy()
    if name == "ant":
        qpos[2] = rng.uniform(0.3, 0.95)
        qvel[:6] = rng.normal(0.0, 3.0, 6)
    else:
        qpos[1:3] = rng.normal(0.0, 0.05, 2)
        qvel[1:3] = rng.normal(0.0, 10.0, 2)
    u.set_state(qpos, qvel)
    return env.observation(u._get_obs())  # env is the outer AppendObservation wrapper


@functools.cache
def transitions(name: str) -> dict[str, torch.Tensor]:
    """Real transitions of env ``name``: obs, act, next_obs, the env's reward and terminated, raw qvel."""
    spec = envs.get(name)
    env = spec.make()
    lo, hi = np.array(spec.action_low), np.array(spec.action_high)
    seeds, smoothings = (0, 1), (0.0, 0.9)
    per = STEPS.get(name, DEFAULT_STEPS) // (len(seeds) * len(smoothings))
    rec: dict[str, list] = {k: [] for k in ("obs", "act", "next_obs", "reward", "terminated", "qvel")}
    for seed in seeds:
        for smooth in smoothings:
            rng = np.random.default_rng(1000 * seed + int(10 * smooth))
            obs, _ = env.reset(seed=seed)
            act = rng.uniform(lo, hi)
            for t in range(per):
                act = smooth * act + (1 - smooth) * rng.uniform(lo, hi)
                nobs, r, term, trunc, _ = env.step(act)
                qvel = env.unwrapped.data.qvel.copy()  # unclipped, for IDP's documented bound
                for k, v in zip(rec, (obs, act, nobs, r, term, qvel)):
                    rec[k].append(v)
                obs = nobs
                if term or trunc:
                    obs, _ = env.reset(seed=int(rng.integers(2**31)))
                    if name in PERTURBED and t % 2 == 0:
                        obs = _perturbed_start(name, env, rng)
                elif name == "ant" and t % 40 == 39:
                    obs = _perturbed_start(name, env, rng)
    env.close()
    out = {k: torch.as_tensor(np.array(v, dtype=np.float64)) for k, v in rec.items() if k != "terminated"}
    out["terminated"] = torch.as_tensor(np.array(rec["terminated"], dtype=bool))
    return out


def reward_errors(name: str) -> tuple[float, float, int, int, int]:
    """(max abs error, max rel error, termination mismatches, transitions, terminal transitions)."""
    d = transitions(name)
    spec = envs.get(name)
    r = spec.reward(d["obs"], d["act"], d["next_obs"])
    term = spec.terminated(d["obs"], d["act"], d["next_obs"])
    err = (r - d["reward"]).abs()
    rel = err / d["reward"].abs().clamp_min(1.0)
    return (
        err.max().item(),
        rel.max().item(),
        int((term != d["terminated"]).sum()),
        len(err),
        int(d["terminated"].sum()),
    )


# --------------------------------------------------------------------------- names


def test_names_are_the_eight_canonical_ones():
    assert NAMES == [
        "invertedpendulum",
        "inverteddoublependulum",
        "reacher",
        "hopper",
        "walker2d",
        "halfcheetah",
        "ant",
        "humanoid",
    ]


@pytest.mark.parametrize(
    "alias,name",
    [
        ("HalfCheetah-v5", "halfcheetah"),
        ("halfcheetah", "halfcheetah"),
        ("HALFCHEETAH", "halfcheetah"),
        ("half_cheetah", "halfcheetah"),
        ("half-cheetah", "halfcheetah"),
        ("Walker2d-v5", "walker2d"),
        ("walker2d", "walker2d"),
        ("InvertedDoublePendulum-v5", "inverteddoublependulum"),
        ("inverted_double_pendulum", "inverteddoublependulum"),
        ("Humanoid-v5", "humanoid"),
        ("ant", "ant"),
        ("Reacher-v5", "reacher"),
        ("Hopper", "hopper"),
        ("InvertedPendulum-v5", "invertedpendulum"),
    ],
)
def test_aliases(alias, name):
    spec = envs.get(alias)
    assert spec.name == name
    assert spec is envs.get(name)  # default specs are cached


@pytest.mark.parametrize("bad", ["cheetah", "HalfCheetah-v4", "pendulum", "", "humanoidstandup"])
def test_unknown_name_lists_valid_names(bad):
    with pytest.raises(ValueError) as info:
        envs.get(bad)
    for n in NAMES:
        assert n in str(info.value)


# --------------------------------------------------------------------------- layouts


def test_layout_validation_rejects_bad_layouts():
    with pytest.raises(ValueError, match="exactly once"):  # index 1 twice, 2 missing
        ObsLayout(obs_dim=3, groups=(Group("a", "Rn", (0, 1)),), velocities=(1,))
    with pytest.raises(ValueError, match="exactly once"):  # out of range
        ObsLayout(obs_dim=2, groups=(Group("a", "SO2_angle", (0,)),), velocities=(2,))
    with pytest.raises(ValueError, match="not Rn"):
        ObsLayout(obs_dim=2, groups=(Group("a", "SO2_angle", (0,)),), velocities=(1,), invariant=(0,))
    with pytest.raises(ValueError, match="expected 4"):
        Group("q", "SO3_quat", (0, 1, 2))
    with pytest.raises(ValueError, match="unknown kind"):
        Group("q", "SE3", (0,))


@pytest.mark.parametrize("name", NAMES)
def test_layout_covers_every_index_once_and_matches_env(name):
    spec = envs.get(name)
    lay = spec.layout
    seen = [i for g in lay.groups for i in g.indices] + [*lay.velocities, *lay.other, *lay.derived]
    assert sorted(seen) == list(range(spec.obs_dim))
    env = spec.make()
    assert env.observation_space.shape == (spec.obs_dim,)
    assert env.action_space.shape == (spec.act_dim,)
    np.testing.assert_array_equal(env.action_space.low, spec.action_low)
    np.testing.assert_array_equal(env.action_space.high, spec.action_high)
    assert spec.dt == pytest.approx(env.unwrapped.dt)
    assert spec.episode_length == env.spec.max_episode_steps == (50 if name == "reacher" else 1000)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (spec.obs_dim,)
    env.close()


INVARIANT = {
    "invertedpendulum": (),
    "inverteddoublependulum": (),
    "reacher": (),
    "hopper": (0,),
    "walker2d": (0,),
    "halfcheetah": (0,),
    "ant": (0, 1, 107),
    "humanoid": (0, 1, 350),
}


@pytest.mark.parametrize("name", NAMES)
def test_layout_entries_mean_what_they_say(name):
    """Every group/velocity/other entry equals the MuJoCo quantity it names, on real states."""
    spec = envs.get(name)
    env = spec.make()
    u = env.unwrapped
    m, d = u.model, u.data
    lay = spec.layout
    assert lay.invariant == INVARIANT[name]
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=3)
    for _ in range(7):
        obs, *_ = env.step(rng.uniform(spec.action_low, spec.action_high))
    qpos, qvel = d.qpos.copy(), d.qvel.copy()

    def adr(joint: str) -> int:
        return int(m.joint(joint).qposadr[0])

    rn_truth = {
        "cart": lambda: qpos[[adr("slider")]],
        "target": lambda: qpos[[adr("target_x"), adr("target_y")]],
        "root_xz": lambda: qpos[[adr("rootx"), adr("rootz")]],
        "torso_pos": lambda: qpos[0:3],
        "main_body_x": lambda: d.body(1).xpos[:1],
        "mass_centre_x": lambda: mass_center(m, d)[:1],
    }
    for g in lay.groups:
        got = obs[list(g.indices)]
        if g.kind == "Rn":
            np.testing.assert_array_equal(got, rn_truth[g.name]())
        elif g.kind == "SO2_angle":
            assert m.joint(g.name).type == 3  # mjJNT_HINGE
            assert got[0] == qpos[adr(g.name)]
        elif g.kind == "SO2_cossin":
            assert m.joint(g.name).type == 3
            np.testing.assert_allclose(got, [np.cos(qpos[adr(g.name)]), np.sin(qpos[adr(g.name)])], atol=1e-15)
        else:  # SO3_quat of the free root joint, (w, x, y, z)
            assert m.joint(0).type == 0 and g.name == "torso_quat"
            np.testing.assert_array_equal(got, qpos[3:7])
            assert np.linalg.norm(got) == pytest.approx(1.0, abs=1e-9)
    # every hinge joint of the model is a group, exactly once
    hinges = {m.joint(j).name for j in range(m.njnt) if m.joint(j).type == 3}
    so2 = [g.name for g in lay.groups if g.kind.startswith("SO2")]
    assert sorted(so2) == sorted(hinges)
    nv = 2 if name == "reacher" else m.nv
    vel_truth = np.clip(qvel[:nv], -10, 10) if name in CLIPPED_VEL else qvel[:nv]
    np.testing.assert_array_equal(obs[list(lay.velocities)], vel_truth)
    other = obs[list(lay.other + lay.derived)]
    if name == "inverteddoublependulum":
        np.testing.assert_array_equal(other, [np.clip(d.qfrc_constraint[0], -10, 10), *d.site_xpos[0][[0, 2]]])
    elif name == "reacher":
        np.testing.assert_array_equal(other, (d.body("fingertip").xpos - d.body("target").xpos)[:2])
    elif name == "ant":
        np.testing.assert_array_equal(other, np.clip(d.cfrc_ext[1:], -1, 1).ravel())
    elif name == "humanoid":
        np.testing.assert_array_equal(
            other,
            np.concatenate([d.cinert[1:].ravel(), d.cvel[1:].ravel(), d.qfrc_actuator[6:], d.cfrc_ext[1:].ravel()]),
        )
    else:
        assert other.size == 0
    env.close()


# --------------------------------------------------------------------------- reward and termination


@pytest.mark.parametrize("name", NAMES)
def test_reward_and_termination_match_simulator(name):
    d = transitions(name)
    spec = envs.get(name)
    r = spec.reward(d["obs"], d["act"], d["next_obs"])
    term = spec.terminated(d["obs"], d["act"], d["next_obs"])
    assert r.shape == d["reward"].shape and r.dtype == torch.float64
    assert term.dtype == torch.bool and term.shape == d["terminated"].shape
    assert torch.equal(term, d["terminated"])
    if name == "inverteddoublependulum":
        # documented: the velocity penalty uses the unclipped qvel; the obs clips it at +-10
        v = d["qvel"]
        bound = 0.001 * (v[:, 1].square() - 100).clamp_min(0) + 0.005 * (v[:, 2].square() - 100).clamp_min(0)
        assert (bound > 0).any(), "the sample should contain clipped velocities"
        err = (r - d["reward"]).abs()
        assert (err <= bound + 1e-9).all()
        assert err[bound == 0].max() < 1e-9
    else:
        torch.testing.assert_close(r, d["reward"], rtol=1e-4, atol=1e-6)
    if name not in ("reacher", "halfcheetah"):
        assert d["terminated"].sum() >= 2, "the sample should include terminal transitions"


@pytest.mark.parametrize("name", NAMES)
def test_float32_and_batch_shapes(name):
    d = transitions(name)
    spec = envs.get(name)
    o, a, n = (d[k][:400] for k in ("obs", "act", "next_obs"))
    r64 = spec.reward(o, a, n)
    r32 = spec.reward(o.float(), a.float(), n.float())
    assert r32.dtype == torch.float32
    # float32 rounding of positions of a few metres, divided by dt: ~1e-7 * |x| / dt
    torch.testing.assert_close(r32.double(), r64, rtol=1e-3, atol=1e-3)
    assert torch.equal(spec.terminated(o.float(), a.float(), n.float()), spec.terminated(o, a, n))
    # arbitrary leading dims, row for row the same as the flat batch
    r3 = spec.reward(o[:24].reshape(2, 3, 4, -1), a[:24].reshape(2, 3, 4, -1), n[:24].reshape(2, 3, 4, -1))
    assert r3.shape == (2, 3, 4)
    torch.testing.assert_close(r3.reshape(-1), r64[:24], rtol=0, atol=0)
    t3 = spec.terminated(o[:24].reshape(4, 6, -1), a[:24].reshape(4, 6, -1), n[:24].reshape(4, 6, -1))
    assert t3.shape == (4, 6)
    # a single transition (no batch dim)
    assert spec.reward(o[0], a[0], n[0]).shape == ()
    assert spec.terminated(o[0], a[0], n[0]).shape == ()


def test_wrong_shapes_raise():
    spec = envs.get("hopper")
    o, a = torch.zeros(5, spec.obs_dim), torch.zeros(5, spec.act_dim)
    with pytest.raises(ValueError, match="obs_dim"):
        spec.reward(o[:, :-1], a, o)
    with pytest.raises(ValueError, match="act_dim"):
        spec.terminated(o, a[:, :-1], o)


def test_inverted_pendulum_non_finite_terminates():
    spec = envs.get("invertedpendulum")
    o = torch.zeros(3, 4)
    n = torch.tensor([[0.0, 0.1, 0.0, 0.0], [0.0, 0.0, float("nan"), 0.0], [0.0, -0.21, 0.0, 0.0]])
    assert spec.terminated(o, torch.zeros(3, 1), n).tolist() == [False, True, True]
    assert spec.reward(o, torch.zeros(3, 1), n).tolist() == [1.0, 0.0, 0.0]


# --------------------------------------------------------------------------- kwargs


def test_overrides_go_through_get_and_stay_consistent():
    spec = envs.get("hopper", ctrl_cost_weight=0.3, healthy_z_range=(0.9, 1.5), terminate_when_unhealthy=False)
    assert spec.params["ctrl_cost_weight"] == 0.3 and spec.params["healthy_z_range"] == (0.9, 1.5)
    env = spec.make()
    u = env.unwrapped
    assert u._ctrl_cost_weight == 0.3
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    rows = []
    for _ in range(150):
        act = rng.uniform(-1, 1, 3)
        nobs, r, term, _, _ = env.step(act)
        rows.append((obs, act, nobs, r, term))
        obs = nobs
    o, a, n = (torch.as_tensor(np.array([row[i] for row in rows])) for i in range(3))
    rew = torch.as_tensor([row[3] for row in rows], dtype=torch.float64)
    torch.testing.assert_close(spec.reward(o, a, n), rew, rtol=1e-4, atol=1e-6)
    assert not spec.terminated(o, a, n).any() and not any(row[4] for row in rows)
    # the healthy bonus did switch off (z left (0.9, 1.5) under random actions) and the reward saw it
    healthy = (n[:, 1] > 0.9) & (n[:, 1] < 1.5) & (n[:, 2].abs() < 0.2)
    assert (~healthy).any()
    env.close()


def test_kwargs_that_change_reward_or_layout_are_refused_where_unsafe():
    with pytest.raises(ValueError, match="envs.get"):
        envs.get("ant").make(ctrl_cost_weight=0.1)
    with pytest.raises(ValueError, match="layout"):
        envs.get("ant", include_cfrc_ext_in_observation=False)
    with pytest.raises(ValueError, match="layout"):
        envs.get("hopper", exclude_current_positions_from_observation=True)
    with pytest.raises(ValueError, match="unknown env kwargs"):
        envs.get("reacher", healthy_reward=1.0)
    env = envs.get("halfcheetah").make(max_episode_steps=7, reset_noise_scale=0.0)  # pass-through kwargs
    assert env.spec.max_episode_steps == 7
    env.close()


# --------------------------------------------------------------------------- edge cases of the v5 sources


def test_healthy_bounds_follow_the_v5_sources():
    """Inclusive/strict bounds and the checks the random rollouts rarely reach."""
    hopper = envs.get("hopper")
    n = torch.zeros(3, hopper.obs_dim, dtype=torch.float64)
    n[:, 1] = 1.25
    n[1, 3] = 150.0  # a joint angle outside healthy_state_range (-100, 100)
    n[2, 2] = 0.2  # pitch exactly at the (open) bound
    a = torch.zeros(3, hopper.act_dim)
    assert hopper.terminated(n, a, n).tolist() == [False, True, True]

    ant = envs.get("ant")  # healthy z range is closed: min_z <= z <= max_z
    n = torch.zeros(4, ant.obs_dim, dtype=torch.float64)
    n[:, 2] = torch.tensor([0.2, 1.0, 1.0 + 1e-9, 0.5], dtype=torch.float64)
    n[3, 20] = float("inf")  # a non-finite qvel entry
    assert ant.terminated(n, torch.zeros(4, 8), n).tolist() == [False, False, True, True]

    hum = envs.get("humanoid")  # healthy z range is open; the contact cost is clipped at 10
    n = torch.zeros(3, hum.obs_dim, dtype=torch.float64)
    n[:, 2] = torch.tensor([1.0, 1.5, 1.5])
    n[2, 272:350] = 1e5  # 5e-7 * 78 * 1e10 >> 10
    a = torch.zeros(3, hum.act_dim)
    assert hum.terminated(n, a, n).tolist() == [True, False, False]
    assert hum.reward(n, a, n).tolist() == [0.0, 5.0, -5.0]


@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def test_functions_run_on_the_inputs_device(device):
    for name in NAMES:
        d = transitions(name)
        spec = envs.get(name)
        o, a, n = (d[k][:64].to(device) for k in ("obs", "act", "next_obs"))
        r, t = spec.reward(o, a, n), spec.terminated(o, a, n)
        assert r.device.type == device and t.device.type == device
        torch.testing.assert_close(r.cpu(), spec.reward(*(d[k][:64] for k in ("obs", "act", "next_obs"))))


def test_spec_is_read_only_and_pickles():
    import pickle

    spec = envs.get("ant")
    with pytest.raises(TypeError):
        spec.params["ctrl_cost_weight"] = 0.0  # type: ignore[index]
    with pytest.raises(Exception):
        spec.dt = 1.0  # type: ignore[misc]
    clone = pickle.loads(pickle.dumps(spec))  # e.g. for subprocess vector envs
    d = transitions("ant")
    o, a, n = (d[k][:50] for k in ("obs", "act", "next_obs"))
    torch.testing.assert_close(clone.reward(o, a, n), spec.reward(o, a, n), rtol=0, atol=0)
    env = clone.make()
    assert env.reset(seed=0)[0].shape == (spec.obs_dim,)
    env.close()


def test_building_envs_prints_no_settotalmass_deprecation(tmp_path) -> None:
    """Issue 17 item 6: MuJoCo printed "compiler attribute 'settotalmass' is deprecated" (from gymnasium's
    half_cheetah.xml) twice per env built, to stderr and to MUJOCO_LOG.TXT; it is dropped, the attribute still
    applies (total mass 14) and other MuJoCo warnings still get through."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    code = (
        "import warnings, mujoco, envs\n"
        "for _ in range(2):\n"
        "    env = envs.get('halfcheetah').make()\n"
        "    mass = float(env.unwrapped.model.body_mass.sum())\n"
        "    env.close()\n"
        "assert abs(mass - 14.0) < 1e-9, mass\n"
        "assert mujoco.get_mju_user_warning() is None  # MuJoCo's own handler is back\n"
        "from envs.spec import _without_settotalmass_warning\n"
        "with warnings.catch_warnings(record=True) as seen, _without_settotalmass_warning():\n"
        "    warnings.simplefilter('always')\n"
        '    m = mujoco.MjModel.from_xml_string(\'<mujoco><compiler settotalmass="2"/>'
        '<worldbody><body><geom size="1"/><joint/></body></worldbody></mujoco>\')\n'
        "    d = mujoco.MjData(m)\n"
        "    d.qvel[:] = float('nan')\n"
        "    mujoco.mj_step(m, d)  # another MuJoCo warning: passed on as a Python warning\n"
        "seen = [str(w.message) for w in seen]\n"
        "assert len(seen) == 1 and seen[0].startswith('MuJoCo: Nan, Inf or huge value'), seen\n"
        "print('done')\n"
    )
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": f"{root}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0 and "done" in proc.stdout, proc.stderr
    assert "settotalmass" not in proc.stdout + proc.stderr
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
