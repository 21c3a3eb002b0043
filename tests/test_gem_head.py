"""Tests of the GEM dynamics head (gem_head.head.GemHead) on real MuJoCo transitions.

Ground truth comes from the simulators (envs.get(name).make(), set_state), scipy.spatial.transform,
torch.autograd.gradcheck and the DeltaHead baseline.
"""

from __future__ import annotations

import math
from functools import cache, partial

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import envs
from dynamics.heads import DeltaHead
from envs.layout import Group, ObsLayout
from gem_head.head import GemHead

ALL_ENVS = envs.names()
COMPOSE = ("right", "left")
SMALL = {"ant": 120, "humanoid": 80}  # env steps per rollout (the slow envs get fewer)


@cache
def rollout(name: str, steps: int = 250, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(obs, act, next_obs) float64 tensors of random-action steps; episodes reset on termination (reset
    transitions included: Ant/Humanoid start with a non-unit quaternion from the reset noise)."""
    steps = SMALL.get(name, steps)
    env = envs.get(name).make()
    env.action_space.seed(seed)
    obs, _ = env.reset(seed=seed)
    o, a, n = [], [], []
    for _ in range(steps):
        act = env.action_space.sample()
        nxt, _, term, trunc, _ = env.step(act)
        o.append(obs), a.append(act), n.append(nxt)
        obs = env.reset()[0] if term or trunc else nxt
    env.close()
    as_t = lambda x: torch.tensor(np.array(x), dtype=torch.float64)  # noqa: E731
    return as_t(o), as_t(a), as_t(n)


def head_of(name: str, **kw) -> GemHead:
    spec = envs.get(name)
    return GemHead(spec.layout, spec.act_dim, **kw)


def assert_close_scaled(got: torch.Tensor, want: torch.Tensor, tol: float) -> None:
    """|got - want| <= tol * (1 + |want|) elementwise (float rounding of deltas scales with the values)."""
    err = ((got.double() - want.double()).abs() / (1.0 + want.double().abs())).max().item()
    assert err <= tol, f"max scaled error {err:.3e} > {tol:.1e}"


def assert_round_trip(head: GemHead, obs: torch.Tensor, nxt: torch.Tensor, tol: float) -> None:
    """next_obs(obs, targets(obs, nxt)) gives nxt on the predicted entries and carries obs on the derived ones."""
    got = head.next_obs(obs, head.targets(obs, nxt))
    pred, derived = list(head.layout.predicted_indices), list(head.layout.derived)
    assert_close_scaled(got[..., pred], nxt[..., pred], tol)
    torch.testing.assert_close(got[..., derived], obs[..., derived], rtol=0, atol=0)


def step_from(env, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(obs, next_obs) of one env step from the state (qpos, qvel)."""
    env.unwrapped.set_state(qpos, qvel)
    obs = env.unwrapped._get_obs()
    if hasattr(env, "observation"):  # the catalogue's AppendObservation wrapper
        obs = env.observation(obs)
    nxt = env.step(act)[0]
    return obs, nxt


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("compose", COMPOSE)
@pytest.mark.parametrize("name", ALL_ENVS)
def test_round_trip_real_transitions(name: str, compose: str) -> None:
    obs, act, nxt = rollout(name)
    head = head_of(name, compose=compose)
    for grp in envs.get(name).layout.groups_of("SO3_quat"):  # the reset row's noisy, non-unit quaternion is covered
        assert (obs[:, list(grp.indices)].norm(dim=-1) - 1).abs().max() > 1e-3
    y = head.targets(obs, nxt)
    assert y.shape == (obs.shape[0], head.target_dim) and torch.isfinite(y).all()
    assert_round_trip(head, obs, nxt, 1e-10)  # float64 (brief: 1e-5)
    o32, n32 = obs.float(), nxt.float()
    assert head.next_obs(o32, head.targets(o32, n32)).dtype == torch.float32
    assert_round_trip(head, o32, n32, 1e-4)
    # leading dims: (E, B, .) batches give the same rows
    e_obs, e_nxt = obs[:40].reshape(4, 10, -1), nxt[:40].reshape(4, 10, -1)
    torch.testing.assert_close(head.targets(e_obs, e_nxt), y[:40].reshape(4, 10, -1), rtol=0, atol=0)
    assert head.inputs(e_obs, act[:40].reshape(4, 10, -1)).shape == (4, 10, head.input_dim)


@pytest.mark.parametrize("name", ["hopper", "walker2d", "halfcheetah", "invertedpendulum"])
def test_planar_targets_equal_delta_targets(name: str) -> None:
    """Rn + hinge-angle layouts: target slot i is observation index i, so targets equal next_obs - obs."""
    obs, _, nxt = rollout(name)
    spec = envs.get(name)
    gem, delta = head_of(name), DeltaHead(spec.layout, spec.act_dim)
    assert gem.target_dim == delta.target_dim == spec.obs_dim
    torch.testing.assert_close(gem.targets(obs, nxt), delta.targets(obs, nxt), rtol=0, atol=1e-15)


def test_hinge_crossing_pi_halfcheetah_rooty() -> None:
    """HalfCheetah's root pitch is unbounded: crossing pi (and several turns out) it is never wrapped."""
    env = envs.get("halfcheetah").make()
    env.reset(seed=1)
    u = env.unwrapped
    for start in (math.pi - 0.02, -math.pi + 0.02, 5 * math.pi - 0.01):
        qpos, qvel = u.init_qpos.copy(), u.init_qvel.copy()
        qpos[1], qpos[2] = 1.0, start  # high up, so no contact
        qvel[2] = 3.0 if start > 0 else -3.0  # towards and across the +-pi (mod 2 pi) boundary
        obs, nxt = step_from(env, qpos, qvel, np.zeros(6))
        assert math.cos(obs[2]) < -0.99 and math.cos(nxt[2]) < -0.99
        assert math.sin(obs[2]) * math.sin(nxt[2]) < 0  # sin changed sign: crossed pi
        o, n = torch.tensor(obs)[None], torch.tensor(nxt)[None]
        for compose in COMPOSE:
            head = head_of("halfcheetah", compose=compose)
            y = head.targets(o, n)
            assert abs(y[0, 2].item() - (nxt[2] - obs[2])) < 1e-12  # the true, small pitch change
            rec = head.next_obs(o, y)
            assert abs(rec[0, 2].item() - nxt[2]) < 1e-12  # unwrapped, like MuJoCo's qpos
            assert_close_scaled(rec, n, 1e-12)
    env.close()


def test_hinge_alpha_is_the_log_of_the_relative_rotation() -> None:
    """For any pair of hinge angles (also 2 pi k apart, and far from 0) alpha = atan2 of R_t^T R_{t+1}."""
    obs, _, nxt = rollout("halfcheetah")
    g = torch.Generator().manual_seed(8)
    o, n = obs[:64].clone(), nxt[:64].clone()
    n[:, 2:9] = (
        o[:, 2:9]
        + (torch.rand(64, 7, generator=g, dtype=torch.float64) * 2 - 1) * 3.1
        + 2 * math.pi * torch.randint(-3, 4, (64, 7), generator=g)
    )
    o[:, 2:9] += 2 * math.pi * torch.randint(-50, 50, (64, 7), generator=g)
    y = head_of("halfcheetah").targets(o, n)[:, 2:9]
    d = n[:, 2:9] - o[:, 2:9]
    torch.testing.assert_close(y, torch.atan2(torch.sin(d), torch.cos(d)), rtol=0, atol=1e-10)
    rec = head_of("halfcheetah").next_obs(o, head_of("halfcheetah").targets(o, n))[:, 2:9]
    torch.testing.assert_close(torch.cos(rec), torch.cos(n[:, 2:9]), rtol=0, atol=1e-10)  # same rotation
    torch.testing.assert_close(torch.sin(rec), torch.sin(n[:, 2:9]), rtol=0, atol=1e-10)


def test_one_wrap_angle_for_targets_and_evaluation() -> None:
    """The head's targets and the offline evaluation wrap with lie.wrap_angle; a hinge step of +-pi gives +pi."""
    from gem_head import head as head_module
    from gem_head import lie
    from pets.learning import evaluation as evaluate

    assert head_module.wrap_angle is lie.wrap_angle
    d = torch.linspace(-40, 40, 8001, dtype=torch.float64)
    assert torch.equal(evaluate.wrap_angle(d), lie.wrap_angle(d))
    head = head_of("invertedpendulum")  # obs 1 is the hinge (SO2_angle)
    o = torch.zeros(4, 4, dtype=torch.float64)
    n = o.clone()
    n[:, 1] = torch.tensor([math.pi, -math.pi, 3 * math.pi, 0.5], dtype=torch.float64)
    y = head.targets(o, n)[:, 1]
    torch.testing.assert_close(y, torch.tensor([math.pi, math.pi, math.pi, 0.5], dtype=torch.float64), rtol=0, atol=0)


@pytest.mark.parametrize("name,joint,nq_hinges", [("reacher", 0, (0, 1)), ("inverteddoublependulum", 1, (1, 2))])
def test_cossin_crossing_pi(name: str, joint: int, nq_hinges: tuple[int, int]) -> None:
    """(cos, sin) hinges whose angle crosses pi: alpha is the true (small) joint motion, the pair round-trips."""
    env = envs.get(name).make()
    env.reset(seed=2)
    u = env.unwrapped
    for direction in (1.0, -1.0):
        qpos, qvel = u.init_qpos.copy(), u.init_qvel.copy()
        qpos[joint] = direction * (math.pi - 0.03)
        qvel[joint] = direction * 4.0
        u.set_state(qpos, qvel)
        q_before = u.data.qpos[list(nq_hinges)].copy()
        obs, nxt = step_from(env, qpos, qvel, np.zeros(env.action_space.shape))
        dq = u.data.qpos[list(nq_hinges)] - q_before
        angle_after = u.data.qpos[joint]
        assert abs(angle_after) > math.pi  # really crossed
        o, n = torch.tensor(obs)[None], torch.tensor(nxt)[None]
        head = head_of(name)
        y = head.targets(o, n)
        alphas = [
            y[0, head.target_names.index(f"alpha {g.name}")].item()
            for g in envs.get(name).layout.groups_of("SO2_cossin")
        ]
        np.testing.assert_allclose(alphas, dq, atol=1e-12)
        assert_close_scaled(head.next_obs(o, y), n, 1e-12)
    env.close()


def _ant_state(seed: int = 3) -> tuple[object, np.ndarray, np.ndarray]:
    env = envs.get("ant").make()
    env.reset(seed=seed)
    env.action_space.seed(seed)
    for _ in range(10):
        env.step(env.action_space.sample())
    return env, env.unwrapped.data.qpos.copy(), env.unwrapped.data.qvel.copy()


@pytest.mark.parametrize("compose", COMPOSE)
def test_quaternion_sign_convention_ant(compose: str) -> None:
    """set_state with q and -q: MuJoCo keeps each sign; the head reproduces whichever the env has."""
    env, qpos, qvel = _ant_state()
    act = np.full(8, 0.3)
    head = head_of("ant", compose=compose)
    results = []
    for sign in (1.0, -1.0):
        qp = qpos.copy()
        qp[3:7] *= sign
        obs, nxt = step_from(env, qp, qvel, act)
        assert np.dot(obs[3:7], nxt[3:7]) > 0.9  # MuJoCo's integration keeps the sign
        o, n = torch.tensor(obs)[None], torch.tensor(nxt)[None]
        y = head.targets(o, n)
        results.append((o, n, y))
        assert_round_trip(head, o, n, 1e-10)
    (o1, n1, y1), (o2, n2, y2) = results
    torch.testing.assert_close(n2[0, 3:7], -n1[0, 3:7], rtol=0, atol=1e-9)  # same physics, opposite sign
    # the targets (positions, alpha, hinges, velocities, main-body x) do not depend on the sign
    torch.testing.assert_close(y2, y1, rtol=0, atol=1e-9)
    # a prediction made from the -q observation stays in the -q convention
    assert_close_scaled(head.next_obs(o2, y1)[:, :29], n2[:, :29], 1e-8)
    env.close()


@pytest.mark.parametrize("compose", COMPOSE)
def test_quaternion_w_crossing_zero_stays_continuous(compose: str) -> None:
    """A torso turning through 180 degrees: w changes sign continuously in MuJoCo; the head follows it."""
    env, qpos, qvel = _ant_state(4)
    qp, qv = qpos.copy(), np.zeros_like(qvel)
    qp[2] = 3.0  # in the air
    half = (math.pi - 0.05) / 2
    qp[3:7] = [math.cos(half), 0.0, 0.0, math.sin(half)]  # yaw of pi - 0.05
    qv[5] = 5.0  # body-frame yaw rate: 0.25 rad in one step
    obs, nxt = step_from(env, qp, qv, np.zeros(8))
    assert obs[3] > 0 > nxt[3]  # w went through zero
    o, n = torch.tensor(obs)[None], torch.tensor(nxt)[None]
    head = head_of("ant", compose=compose)
    y = head.targets(o, n)
    assert abs(y[0, 5].item() - 0.25) < 0.02 and abs(y[0, 3:5]).max() < 0.02  # a small yaw step, not ~2 pi
    assert_close_scaled(head.next_obs(o, y), n, 1e-10)
    env.close()


@pytest.mark.parametrize("compose", COMPOSE)
def test_large_alpha_keeps_quaternion_sign_continuous(compose: str) -> None:
    """|alpha| in (pi, 2 pi) (possible for sampled targets): the rotation is exp(alpha) (scipy), the sign the one
    with dot(q', q) >= 0."""
    obs, _, _ = rollout("ant")
    head = head_of("ant", compose=compose)
    g = torch.Generator().manual_seed(7)
    o = obs[1:41]
    axis = torch.nn.functional.normalize(torch.randn(40, 3, generator=g, dtype=torch.float64), dim=-1)
    angle = torch.linspace(0.1, 2 * math.pi - 0.1, 40, dtype=torch.float64)
    target = torch.zeros(40, head.target_dim, dtype=torch.float64)
    target[:, 3:6] = axis * angle[:, None]
    q = head.next_obs(o, target)[:, 3:7]
    assert ((q * o[:, 3:7]).sum(-1) >= 0).all()
    r0, step = Rotation.from_quat(o[:, [4, 5, 6, 3]].numpy()), Rotation.from_rotvec(target[:, 3:6].numpy())
    want = r0 * step if compose == "right" else step * r0
    assert (Rotation.from_quat(q[:, [1, 2, 3, 0]].numpy()).inv() * want).magnitude().max() < 1e-12


def test_left_and_right_targets_differ_and_are_related_by_the_rotation() -> None:
    """alpha_left = R_t alpha_right (adjoint of SO(3)); both round-trip exactly (see above)."""
    obs, _, nxt = rollout("ant")
    right, left = head_of("ant", compose="right"), head_of("ant", compose="left")
    yr, yl = right.targets(obs, nxt)[:, 3:6], left.targets(obs, nxt)[:, 3:6]
    q = obs[:, 3:7].numpy()
    rot = Rotation.from_quat(q[:, [1, 2, 3, 0]])  # scipy is scalar-last (and normalises)
    np.testing.assert_allclose(yl.numpy(), rot.apply(yr.numpy()), atol=1e-12)
    assert (yl - yr).abs().max() > 1e-2
    # and the right target is the scipy relative rotation vector R_t^T R_{t+1}
    rot_next = Rotation.from_quat(nxt[:, [4, 5, 6, 3]].numpy())
    np.testing.assert_allclose(yr.numpy(), (rot.inv() * rot_next).as_rotvec(), atol=1e-12)


# ----------------------------------------------------------------------------- inputs


@pytest.mark.parametrize("name", ["hopper", "walker2d", "halfcheetah", "ant", "humanoid"])
def test_invariant_coordinates_never_enter_inputs(name: str) -> None:
    obs, act, nxt = rollout(name)
    spec = envs.get(name)
    head = head_of(name)
    inv = list(spec.layout.invariant)
    shift = torch.zeros(spec.obs_dim, dtype=torch.float64)
    shift[inv] = torch.linspace(3.0, 11.0, len(inv), dtype=torch.float64)
    torch.testing.assert_close(head.inputs(obs + shift, act), head.inputs(obs, act), rtol=0, atol=0)
    y = head.targets(obs, nxt)
    torch.testing.assert_close(head.targets(obs + shift, nxt + shift), y, rtol=0, atol=1e-12)
    torch.testing.assert_close(head.next_obs(obs + shift, y), head.next_obs(obs, y) + shift, rtol=0, atol=1e-12)
    assert not any(f"obs[{i}]" == n for i in inv for n in head.input_names)


def test_input_encoding_ant() -> None:
    """Ant inputs: z and velocities pass through; hinges as cos/sin; torso as its 9 rotation entries; the
    contact forces (derived) are not inputs."""
    obs, act, _ = rollout("ant")
    head = head_of("ant")
    x = head.inputs(obs, act)
    assert x.shape == (obs.shape[0], 1 + 14 + 2 * 8 + 9 + 8) == (obs.shape[0], head.input_dim)
    assert not any(f"obs[{i}]" in head.input_names for i in envs.get("ant").layout.derived)
    names = head.input_names
    np.testing.assert_allclose(x[:, names.index("obs[2]")], obs[:, 2])
    np.testing.assert_allclose(x[:, names.index("cos obs[7]")], torch.cos(obs[:, 7]))
    k = names.index("R00 of obs[3:7]")
    want = Rotation.from_quat(obs[:, [4, 5, 6, 3]].numpy()).as_matrix().reshape(-1, 9)
    np.testing.assert_allclose(x[:, k : k + 9].numpy(), want, atol=1e-12)
    np.testing.assert_allclose(x[:, -8:], act)


# ----------------------------------------------------------------------------- manifold


@pytest.mark.parametrize("name", ["ant", "humanoid", "inverteddoublependulum", "reacher"])
@settings(max_examples=6, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    scale=st.floats(0.05, 0.5),
    dtype=st.sampled_from([torch.float32, torch.float64]),
    compose=st.sampled_from(COMPOSE),
)
def test_states_stay_on_the_manifold_over_100_steps(
    name: str, seed: int, scale: float, dtype: torch.dtype, compose: str
) -> None:
    obs, _, _ = rollout(name)
    head = head_of(name, compose=compose)
    g = torch.Generator().manual_seed(seed)
    start = obs[1:9].to(dtype)  # real (post-step) observations; row 0 of Ant/Humanoid is a reset one
    alphas = (torch.rand(100, *start.shape[:-1], head.target_dim, generator=g, dtype=torch.float64) * 2 - 1) * scale
    x = start
    for k in range(100):
        x = head.next_obs(x, alphas[k].to(dtype))
    assert torch.isfinite(x).all()
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    layout = envs.get(name).layout
    for grp in layout.groups_of("SO3_quat"):
        q = x[..., list(grp.indices)].double()
        assert (q.norm(dim=-1) - 1).abs().max() <= tol
        # ground truth: the composition of the 100 exponentials, by scipy
        t = [head.target_names.index(f"alpha {grp.name}[{a}]") for a in "xyz"]
        rot = Rotation.from_quat(start[..., [grp.indices[i] for i in (1, 2, 3, 0)]].double().numpy())
        for k in range(100):
            step = Rotation.from_rotvec(alphas[k][..., t].to(dtype).double().numpy())
            rot = rot * step if compose == "right" else step * rot
        got = Rotation.from_quat(q[..., [1, 2, 3, 0]].numpy())
        assert (got.inv() * rot).magnitude().max() < (1e-9 if dtype == torch.float64 else 1e-4)
    for grp in layout.groups_of("SO2_cossin"):
        c, s = x[..., grp.indices[0]].double(), x[..., grp.indices[1]].double()
        assert (c * c + s * s - 1).abs().max() <= tol * 2
    for grp in layout.groups_of("SO2_angle"):  # hinges: start + sum of alphas, never wrapped
        i = grp.indices[0]
        t = head.target_names.index(f"alpha {grp.name}")
        want = start[..., i].double() + alphas[..., t].to(dtype).double().sum(0)
        assert (x[..., i].double() - want).abs().max() < (1e-10 if dtype == torch.float64 else 1e-4)


# ----------------------------------------------------------------------------- gem == delta where it must


def _rn_only_layout() -> ObsLayout:
    """HalfCheetah's observation with every position declared a translation (no rotation groups)."""
    return ObsLayout(
        obs_dim=18,
        groups=(Group("root_xz", "Rn", (0, 1)), Group("angles", "Rn", tuple(range(2, 9)))),
        velocities=tuple(range(9, 18)),
        invariant=(0,),
    )


def test_rn_only_layout_gem_equals_delta() -> None:
    obs, act, nxt = rollout("halfcheetah")
    layout = _rn_only_layout()
    gem, delta = GemHead(layout, 6), DeltaHead(layout, 6)
    assert (gem.input_dim, gem.target_dim) == (delta.input_dim, delta.target_dim)
    torch.testing.assert_close(gem.inputs(obs, act), delta.inputs(obs, act), rtol=0, atol=0)
    y = gem.targets(obs, nxt)
    torch.testing.assert_close(y, delta.targets(obs, nxt), rtol=0, atol=0)
    sample = y + 0.1 * torch.randn_like(y)
    torch.testing.assert_close(gem.next_obs(obs, sample), delta.next_obs(obs, sample), rtol=0, atol=0)
    # same inputs, targets and loss: a GaussianEnsemble trained from the same seed predicts the same
    from dynamics.networks import GaussianEnsemble

    preds = []
    for head in (gem, delta):
        torch.manual_seed(0)
        ens = GaussianEnsemble(head.input_dim, head.target_dim, ensemble_size=3, hidden_size=32, num_layers=2)
        x, t = head.inputs(obs, act).float(), head.targets(obs, nxt).float()
        ens.fit_normaliser(x)
        opt = torch.optim.Adam(ens.parameters(), lr=1e-3)
        for _ in range(20):
            idx = torch.randint(0, x.shape[0], (3, 32))
            mean, logvar = ens(x[idx])
            loss = head.loss(mean, logvar, t[idx], obs[idx].float(), nxt[idx].float()).sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            preds.append(head.next_obs(obs.float(), ens(x)[0][0]))
    torch.testing.assert_close(preds[0], preds[1], rtol=0, atol=0)


# ----------------------------------------------------------------------------- losses


@pytest.mark.parametrize("compose", COMPOSE)
@pytest.mark.parametrize("name", ["ant", "inverteddoublependulum", "halfcheetah"])
def test_frobenius_zero_at_true_alpha(name: str, compose: str) -> None:
    obs, _, nxt = rollout(name)
    head = head_of(name, compose=compose, loss="frobenius")
    o, n = obs[1:61].reshape(3, 20, -1), nxt[1:61].reshape(3, 20, -1)
    y = head.targets(o, n)
    frob = head.frobenius_loss(y, y, o, n)
    assert frob.shape == (3,) and frob.abs().max() < 1e-24


@pytest.mark.parametrize("compose", COMPOSE)
def test_frobenius_closed_form_so3_and_so2(compose: str) -> None:
    """||R1 - R2||_F^2 = 8 sin^2(phi/2) for a rotation error phi (scipy measures phi)."""
    obs, _, nxt = rollout("ant")
    head = head_of("ant", compose=compose)
    o, n = obs[1:41].unsqueeze(1), nxt[1:41].unsqueeze(1)  # (E=40, B=1, .): one loss value per row
    y = head.targets(o, n)
    g = torch.Generator().manual_seed(5)
    mean = y.clone()
    mean[..., 3:6] += torch.randn(40, 1, 3, generator=g, dtype=torch.float64) * 0.7
    per_row = head.frobenius_loss(mean, y, o, n) * head.target_dim
    r0 = Rotation.from_quat(o[:, 0][:, [4, 5, 6, 3]].numpy())
    step = Rotation.from_rotvec(mean[:, 0, 3:6].numpy())
    pred = r0 * step if compose == "right" else step * r0
    phi = (pred.inv() * Rotation.from_quat(n[:, 0][:, [4, 5, 6, 3]].numpy())).magnitude()
    assert phi.max() > 1.0
    np.testing.assert_allclose(per_row.numpy(), 8 * np.sin(phi / 2) ** 2, rtol=1e-10, atol=1e-14)
    # SO(2): a hinge alpha off by d gives 8 sin^2(d/2); a velocity off by v gives v^2 (all / target_dim)
    mean = y.clone()
    d = torch.linspace(-3.0, 3.0, 40, dtype=torch.float64)
    mean[:, 0, head.target_names.index("alpha hip_1")] += d
    mean[:, 0, head.target_names.index("d vel[15]")] += 0.5
    per_row = head.frobenius_loss(mean, y, o, n) * head.target_dim
    np.testing.assert_allclose(per_row.numpy(), 8 * torch.sin(d / 2).square().numpy() + 0.25, rtol=1e-10)


def test_losses_gradients_and_modes() -> None:
    obs, _, nxt = rollout("ant")
    o, n = obs[1:25].reshape(2, 12, -1), nxt[1:25].reshape(2, 12, -1)
    base = head_of("ant")
    y = base.targets(o, n)
    g = torch.Generator().manual_seed(6)
    mean0 = y + 0.3 * torch.randn(y.shape, generator=g, dtype=torch.float64)
    logvar0 = 0.2 * torch.randn(y.shape, generator=g, dtype=torch.float64)
    # gradcheck of the Frobenius loss (float64), away from and exactly at the true alpha
    for compose in COMPOSE:
        head = head_of("ant", compose=compose)
        for m in (mean0, y):
            mm = m[:, :3].clone().requires_grad_(True)
            assert torch.autograd.gradcheck(
                partial(head.frobenius_loss, target=y[:, :3], obs=o[:, :3], next_obs=n[:, :3]), (mm,)
            )
    frob_ref = head_of("ant").frobenius_loss(mean0, y, o, n)
    from dynamics.losses import gaussian_nll

    nll_ref = gaussian_nll(mean0, logvar0, y)
    for kind, w in (("nll", 1.0), ("frobenius", 1.0), ("nll+frobenius", 0.3)):
        head = head_of("ant", loss=kind, frobenius_weight=w)
        mean, logvar = mean0.clone().requires_grad_(True), logvar0.clone().requires_grad_(True)
        out = head.loss(mean, logvar, y, o, n)
        assert out.shape == (2,)
        want = {"nll": nll_ref, "frobenius": frob_ref + nll_ref, "nll+frobenius": nll_ref + 0.3 * frob_ref}[kind]
        torch.testing.assert_close(out, want, rtol=1e-12, atol=1e-12)
        out.sum().backward()
        assert torch.isfinite(mean.grad).all() and torch.isfinite(logvar.grad).all() and logvar.grad.abs().sum() > 0
        if kind == "frobenius":  # the mean gets only the Frobenius gradient, the NLL sees it detached
            m2 = mean0.clone().requires_grad_(True)
            head.frobenius_loss(m2, y, o, n).sum().backward()
            torch.testing.assert_close(mean.grad, m2.grad, rtol=1e-12, atol=1e-15)


# ----------------------------------------------------------------------------- errors


def test_bad_arguments_raise_value_error() -> None:
    spec = envs.get("ant")
    with pytest.raises(ValueError, match="compose"):
        GemHead(spec.layout, spec.act_dim, compose="middle")
    with pytest.raises(ValueError, match="loss"):
        GemHead(spec.layout, spec.act_dim, loss="mse")
    with pytest.raises(ValueError, match="frobenius_weight"):
        GemHead(spec.layout, spec.act_dim, frobenius_weight=-1.0)
    with pytest.raises(ValueError, match="act_dim"):
        GemHead(spec.layout, 0)
    head = GemHead(spec.layout, spec.act_dim)
    obs = torch.zeros(3, spec.obs_dim)
    with pytest.raises(ValueError, match=r"obs must have shape \(\.\.\., 108\)"):
        head.inputs(obs[:, :-1], torch.zeros(3, 8))
    with pytest.raises(ValueError, match="act must have shape"):
        head.inputs(obs, torch.zeros(3, 7))
    with pytest.raises(ValueError, match="next_obs must have shape"):
        head.targets(obs, obs[:, :10])
    with pytest.raises(ValueError, match=r"target must have shape \(\.\.\., 29\)"):
        head.next_obs(obs, torch.zeros(3, 108))
    with pytest.raises(ValueError, match="floating-point"):
        head.next_obs(obs.long(), torch.zeros(3, 29))
    with pytest.raises(ValueError, match=r"\(E, B, \.\)"):
        head.loss(torch.zeros(29), torch.zeros(29), torch.zeros(29), obs[0], obs[0])
    with pytest.raises(ValueError, match="logvar must have shape"):
        head.loss(torch.zeros(2, 3, 29), torch.zeros(2, 3, 28), torch.zeros(2, 3, 29), obs, obs)
