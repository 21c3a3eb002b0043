"""gem-se (gem_head.se_root): the floating root on SE(2)/SE(3) in the body frame, against real MuJoCo trajectories
and MuJoCo's own body frames; invariance to where the body is; gradients; the refusal where there is no root."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch

import envs
from gem_head.head import GemHead
from gem_head.lie import SE2, SE3, SO3
from gem_head.se_root import GemSEHead
from pets.data.rollout import collect_random

ROOTED = ["hopper", "walker2d", "halfcheetah", "ant", "humanoid"]
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def transitions(env: str, n: int = 300) -> tuple[envs.EnvSpec, torch.Tensor, torch.Tensor]:
    spec = envs.get(env)
    obs, _, nxt = (torch.as_tensor(x, dtype=torch.float64) for x in collect_random(spec, n, 0))
    return spec, obs, nxt


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return SO3.quat_mul(a, b)


def assert_same_state(spec: envs.EnvSpec, got: torch.Tensor, want: torch.Tensor) -> None:
    """Every predicted entry equal to 1e-10, quaternions as rotations (the decoded one is unit, the observed one
    is not right after a reset)."""
    quat = [i for g in spec.layout.groups_of("SO3_quat") for i in g.indices]
    plain = [i for i in spec.layout.predicted_indices if i not in quat]
    torch.testing.assert_close(got[:, plain], want[:, plain], rtol=0, atol=1e-10)
    if quat:
        r = [SO3.from_quat(x[:, quat] / x[:, quat].norm(dim=-1, keepdim=True)) for x in (got, want)]
        torch.testing.assert_close(r[0], r[1], rtol=0, atol=1e-10)


@pytest.mark.parametrize("env", ROOTED)
def test_targets_decode_back_to_the_real_next_observation(env: str) -> None:
    spec, obs, nxt = transitions(env)
    head = GemSEHead(spec.layout, spec.act_dim)
    assert_same_state(spec, head.next_obs(obs, head.targets(obs, nxt)), nxt)
    # Only the root's translation slots differ from gem's targets.
    gem = GemHead(spec.layout, spec.act_dim).targets(obs, nxt)
    changed = torch.nonzero((head.targets(obs, nxt) - gem).abs().amax(0) > 1e-12).flatten().tolist()
    assert changed == list(head.target_slots_of(spec.layout.root[0]))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("env", ROOTED)
def test_inputs_targets_and_decoding_agree_across_devices(env: str, device: str) -> None:
    """The head on the data's device (CUDA where present) gives the CPU's float64 inputs and targets, and decodes
    back to the real next observation."""
    spec, obs, nxt = transitions(env, 100)
    head = GemSEHead(spec.layout, spec.act_dim)
    act = torch.rand(len(obs), spec.act_dim, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    want_targets, want_inputs = head.targets(obs, nxt), head.inputs(obs, act)
    o, n, a = obs.to(device), nxt.to(device), act.to(device)
    targets = head.targets(o, n)
    assert targets.device.type == device
    torch.testing.assert_close(targets.cpu(), want_targets, rtol=0, atol=1e-12)
    torch.testing.assert_close(head.inputs(o, a).cpu(), want_inputs, rtol=0, atol=1e-12)
    assert_same_state(spec, head.next_obs(o, targets).cpu(), nxt)


@pytest.mark.parametrize("env", ["halfcheetah", "hopper"])
def test_planar_round_trip_with_the_pitch_near_plus_and_minus_pi(env: str) -> None:
    spec, obs, nxt = transitions(env, 100)
    head = GemSEHead(spec.layout, spec.act_dim)
    for offset in (math.pi - 1e-3, -math.pi + 1e-3, 7 * math.pi):  # hinge positions are unbounded in MuJoCo
        o, n = obs.clone(), nxt.clone()
        o[:, 2] += offset
        n[:, 2] += offset
        assert_same_state(spec, head.next_obs(o, head.targets(o, n)), n)


@pytest.mark.parametrize("env", ["ant", "humanoid"])
def test_round_trip_with_the_torso_upside_down(env: str) -> None:
    spec, obs, nxt = transitions(env, 100)
    head = GemSEHead(spec.layout, spec.act_dim)
    flip = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=torch.float64)  # 180 degrees about x
    o, n = obs.clone(), nxt.clone()
    o[:, 3:7], n[:, 3:7] = quat_mul(flip, obs[:, 3:7]), quat_mul(flip, nxt[:, 3:7])
    assert_same_state(spec, head.next_obs(o, head.targets(o, n)), n)


def _move_world_3d(x: torch.Tensor, q_world: torch.Tensor, p_world: torch.Tensor) -> torch.Tensor:
    """The torso moved by the rigid motion (R_w, p_w): p -> R_w p + p_w, q -> q_w q."""
    out = x.clone()
    out[:, 0:3] = x[:, 0:3] @ SO3.from_quat(q_world).T + p_world
    out[:, 3:7] = quat_mul(q_world.expand(len(x), 4), x[:, 3:7])
    return out


def _move_world_planar(x: torch.Tensor, phi: float, p_world: torch.Tensor) -> torch.Tensor:
    """The planar root moved by the SE(2) motion (R(phi), p_w) of the x-z plane: the pitch turns by -phi."""
    out = x.clone()
    c, s = math.cos(phi), math.sin(phi)
    out[:, 0:2] = x[:, 0:2] @ torch.tensor([[c, -s], [s, c]], dtype=x.dtype).T + p_world
    out[:, 2] = x[:, 2] - phi
    return out


@pytest.mark.parametrize("env", ["ant", "halfcheetah"])
def test_root_targets_do_not_depend_on_where_the_body_is(env: str) -> None:
    """A body-frame twist is the same wherever the world puts the body (heading, tilt, position); gem's world-frame
    translation target is not (the contrast shows the check can fail)."""
    spec, obs, nxt = transitions(env, 200)
    if env == "ant":
        axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
        half = 1.1  # a 2.2 rad rotation about a tilted axis
        q_w = torch.cat([torch.tensor([math.cos(half)]), math.sin(half) * axis / axis.norm()])
        p_w = torch.tensor([5.0, -3.0, 0.7], dtype=torch.float64)
        moved = [_move_world_3d(x, q_w, p_w) for x in (obs, nxt)]
    else:
        p_w = torch.tensor([4.0, 0.3], dtype=torch.float64)
        moved = [_move_world_planar(x, 0.9, p_w) for x in (obs, nxt)]
    se, gem = GemSEHead(spec.layout, spec.act_dim), GemHead(spec.layout, spec.act_dim)
    root = [*se.target_slots_of(spec.layout.root[0]), *se.target_slots_of(spec.layout.root[1])]
    torch.testing.assert_close(se.targets(*moved)[:, root], se.targets(obs, nxt)[:, root], rtol=0, atol=1e-9)
    translation = list(se.target_slots_of(spec.layout.root[0]))
    assert (gem.targets(*moved)[:, translation] - gem.targets(obs, nxt)[:, translation]).abs().max() > 1e-3


@pytest.mark.parametrize("env", ["halfcheetah", "ant"])
def test_root_rotation_is_mujocos_body_frame(env: str) -> None:
    """The rotation the head reads from the observation is MuJoCo's own orientation of the root body (``xmat``):
    for the planar root, R(-pitch) in the x-z plane."""
    spec = envs.get(env)
    gym_env = spec.make()
    obs, _ = gym_env.reset(seed=3)
    model, data = gym_env.unwrapped.model, gym_env.unwrapped.data
    head = GemSEHead(spec.layout, spec.act_dim)
    rng = np.random.default_rng(0)
    for _ in range(5):
        if env == "halfcheetah":
            data.qpos[2] = rng.uniform(-3, 3)
        else:
            q = rng.normal(size=4)
            data.qpos[3:7] = q / np.linalg.norm(q)
        mujoco.mj_forward(model, data)
        obs = torch.as_tensor(gym_env.unwrapped._get_obs(), dtype=torch.float64)
        xmat = data.xmat[model.body("torso").id].reshape(3, 3)
        want = xmat[np.ix_([0, 2], [0, 2])] if env == "halfcheetah" else xmat
        np.testing.assert_allclose(head.root_codec.rotation(obs).numpy(), want, atol=1e-9)
    gym_env.close()


@pytest.mark.parametrize("group", [SE2, SE3])
def test_the_translation_maps_are_inverse_differentiable_and_match_exp_and_log(group) -> None:
    """u -> V(w) u (decoding) and t -> V(w)^-1 t (encoding): inverse to each other, the translation column of
    ``group.exp`` and the translation part of ``group.log``, with gradients (gradcheck) also at w = 0 and near pi."""
    gen = torch.Generator().manual_seed(0)
    k = 1 if group is SE2 else 3
    w = torch.randn(6, k, generator=gen, dtype=torch.float64)
    w[0] = 0.0
    w[1] = w[1] / w[1].norm() * (math.pi - 1e-6)
    w = w[:, 0] if group is SE2 else w
    u = torch.randn(6, k if group is SE3 else 2, generator=gen, dtype=torch.float64)
    twist = torch.cat([w.reshape(6, -1), u], dim=-1)
    t = group.v_apply(w, u)
    n = 2 if group is SE2 else 3
    torch.testing.assert_close(t, group.exp(twist)[..., :n, n], rtol=0, atol=1e-12)
    torch.testing.assert_close(group.v_inv_apply(w, t), u, rtol=0, atol=1e-9)
    torch.testing.assert_close(group.log(group.exp(twist))[..., -n:], u, rtol=0, atol=1e-9)
    for fn, x in ((group.v_apply, u), (group.v_inv_apply, t)):
        assert torch.autograd.gradcheck(fn, (w.clone().requires_grad_(), x.clone().requires_grad_()))


def test_gem_se_needs_a_floating_root_and_the_body_frame(capsys) -> None:
    import run_pets

    for argv, fragment in (
        (["--env", "reacher", "--model", "gem-se"], "reacher has none; it applies to hopper, walker2d, halfcheetah"),
        (["--env", "ant", "--model", "gem-se", "gem.compose=left"], "gem.compose must be right"),
    ):
        with pytest.raises(SystemExit) as exc:
            run_pets.main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 2 and len(err) == 1 and fragment in err[0], err
    with pytest.raises(ValueError, match="layout has none"):
        spec = envs.get("reacher")
        GemSEHead(spec.layout, spec.act_dim)
