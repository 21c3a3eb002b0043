"""The eight gymnasium MuJoCo v5 environments: layouts, rewards, terminations.

Observations are the v5 ones with ``exclude_current_positions_from_observation=False`` (root x,
and y for Ant/Humanoid, at the front) so that rewards are functions of ``(obs, act, next_obs)``.
InvertedDoublePendulum, Ant and Humanoid get appended entries: the positions their rewards read from
MuJoCo's ``data`` after ``mj_step``. Those come from the kinematics of the last RK4 stage, not of the
final ``qpos`` (IDP tip: up to 1e-4 m apart in free motion, 1e-2 m when the cart hits the rail end;
Ant torso x: up to ~3e-4 m, i.e. ~7e-3 reward), so recomputing them from the observed ``qpos`` would
not give the env's reward; appending them does. Every reward/termination below
mirrors ``gymnasium/envs/mujoco/<env>_v5.py`` line by line; constants come from the built env.

Index maps (obs_dim; "vel" = MuJoCo qvel entries, clipped to +-10 where noted):

- invertedpendulum (4): 0 cart x | 1 hinge | 2-3 vel.
- inverteddoublependulum (11): 0 cart x | 1 sin q1, 2 sin q2, 3 cos q1, 4 cos q2 | 5-7 vel (clipped)
  | 8 slider constraint force (clipped) | 9-10 appended tip site (x, z) = ``data.site_xpos[0]``.
- reacher (10): 0 cos q0, 1 cos q1, 2 sin q0, 3 sin q1 | 4-5 target x, y | 6-7 joint vel
  | 8-9 fingertip - target (x, y).
- hopper (12): 0 x, 1 z | 2 pitch, 3-5 joints | 6-11 vel (clipped).
- walker2d (18): 0 x, 1 z | 2 pitch, 3-8 joints | 9-17 vel (clipped).
- halfcheetah (18): 0 x, 1 z | 2 pitch, 3-8 joints | 9-17 vel.
- ant (108): 0-2 torso x, y, z | 3-6 quaternion w, x, y, z | 7-14 hinges | 15-28 vel (3 linear
  world, 3 angular body, 8 joints) | 29-106 derived: contact forces cfrc_ext[1:] clipped to [-1, 1]
  | 107 appended main-body x (``data.body(main_body).xpos[0]``, what the forward reward differences).
- humanoid (351): 0-2 torso x, y, z | 3-6 quaternion | 7-23 hinges | 24-46 vel (6 free + 17)
  | derived: 47-176 cinert, 177-254 cvel, 255-271 qfrc_actuator, 272-349 cfrc_ext[1:] | 350 appended
  mass-centre x (gymnasium's ``mass_center``, what the forward reward differences).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from functools import partial
from typing import Any

import gymnasium
import numpy as np
import torch
from torch import Tensor

from envs.layout import Group, ObsLayout
from envs.spec import AppendObservation, EnvSpec, ReadOnlyDict, env_constructor_params, gymnasium_make

# --------------------------------------------------------------------------- layouts

PLANAR_JOINTS = {
    "hopper": ("thigh_joint", "leg_joint", "foot_joint"),
    "walker2d": ("thigh_joint", "leg_joint", "foot_joint", "thigh_left_joint", "leg_left_joint", "foot_left_joint"),
    "halfcheetah": ("bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot"),
}
ANT_HINGES = ("hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3", "hip_4", "ankle_4")
HUMANOID_HINGES = (
    "abdomen_z",
    "abdomen_y",
    "abdomen_x",
    "right_hip_x",
    "right_hip_z",
    "right_hip_y",
    "right_knee",
    "left_hip_x",
    "left_hip_z",
    "left_hip_y",
    "left_knee",
    "right_shoulder1",
    "right_shoulder2",
    "right_elbow",
    "left_shoulder1",
    "left_shoulder2",
    "left_elbow",
)

IDP_TIP = (9, 10)
ANT_NQ, ANT_NV = 15, 14
ANT_CFRC = (ANT_NQ + ANT_NV, ANT_NQ + ANT_NV + 78)  # [29, 107)
ANT_XREF = 107
HUM_NQ, HUM_NV = 24, 23
HUM_CINERT = (47, 177)
HUM_CVEL = (177, 255)
HUM_QFRC = (255, 272)
HUM_CFRC = (272, 350)
HUM_COMX = 350


def _r(a: int, b: int) -> tuple[int, ...]:
    return tuple(range(a, b))


def pendulum_layout() -> ObsLayout:
    return ObsLayout(
        obs_dim=4, groups=(Group("cart", "Rn", (0,)), Group("hinge", "SO2_angle", (1,))), velocities=(2, 3)
    )


def double_pendulum_layout() -> ObsLayout:
    return ObsLayout(
        obs_dim=11,
        groups=(Group("cart", "Rn", (0,)), Group("hinge", "SO2_cossin", (3, 1)), Group("hinge2", "SO2_cossin", (4, 2))),
        velocities=(5, 6, 7),
        other=(8, *IDP_TIP),
    )


def reacher_layout() -> ObsLayout:
    return ObsLayout(
        obs_dim=10,
        groups=(
            Group("joint0", "SO2_cossin", (0, 2)),
            Group("joint1", "SO2_cossin", (1, 3)),
            Group("target", "Rn", (4, 5)),
        ),
        velocities=(6, 7),
        other=(8, 9),
    )


def planar_layout(joints: tuple[str, ...]) -> ObsLayout:
    """Hopper/Walker2d/HalfCheetah: qpos = (rootx, rootz, rooty, joints...), then qvel."""
    nq = 3 + len(joints)
    groups = (
        Group("root_xz", "Rn", (0, 1)),
        Group("rooty", "SO2_angle", (2,)),
        *(Group(j, "SO2_angle", (3 + k,)) for k, j in enumerate(joints)),
    )
    return ObsLayout(
        obs_dim=2 * nq, groups=groups, velocities=_r(nq, 2 * nq), invariant=(0,), root=("root_xz", "rooty")
    )


def ant_layout() -> ObsLayout:
    groups = (
        Group("torso_pos", "Rn", (0, 1, 2)),
        Group("torso_quat", "SO3_quat", (3, 4, 5, 6)),
        *(Group(j, "SO2_angle", (7 + k,)) for k, j in enumerate(ANT_HINGES)),
        Group("main_body_x", "Rn", (ANT_XREF,)),
    )
    return ObsLayout(
        obs_dim=ANT_XREF + 1,
        groups=groups,
        velocities=_r(ANT_NQ, ANT_NQ + ANT_NV),
        derived=_r(*ANT_CFRC),
        invariant=(0, 1, ANT_XREF),
        root=("torso_pos", "torso_quat"),
    )


def humanoid_layout() -> ObsLayout:
    groups = (
        Group("torso_pos", "Rn", (0, 1, 2)),
        Group("torso_quat", "SO3_quat", (3, 4, 5, 6)),
        *(Group(j, "SO2_angle", (7 + k,)) for k, j in enumerate(HUMANOID_HINGES)),
        Group("mass_centre_x", "Rn", (HUM_COMX,)),
    )
    return ObsLayout(
        obs_dim=HUM_COMX + 1,
        groups=groups,
        velocities=_r(HUM_NQ, HUM_NQ + HUM_NV),
        derived=_r(HUM_CINERT[0], HUM_CFRC[1]),
        invariant=(0, 1, HUM_COMX),
        root=("torso_pos", "torso_quat"),
    )


# --------------------------------------------------------------------------- rewards / terminations
# All functions: (p: dict of constants, obs, act, next_obs) -> Tensor (...). `p` is bound by partial.


def _ctrl_cost(w: float, act: Tensor) -> Tensor:
    return w * act.square().sum(-1)


def _never(p: dict, obs: Tensor, act: Tensor, nobs: Tensor) -> Tensor:
    return torch.zeros(nobs.shape[:-1], dtype=torch.bool, device=nobs.device)


def _ip_terminated(p: dict, obs: Tensor, act: Tensor, nobs: Tensor) -> Tensor:
    return ~torch.isfinite(nobs).all(-1) | (nobs[..., 1].abs() > p["max_abs_angle"])


def _ip_reward(p: dict, obs: Tensor, act: Tensor, nobs: Tensor) -> Tensor:
    return (~_ip_terminated(p, obs, act, nobs)).to(nobs.dtype)


def _idp_terminated(p: dict, obs: Tensor, act: Tensor, nobs: Tensor) -> Tensor:
    return nobs[..., IDP_TIP[1]] <= p["min_tip_height"]


def _idp_reward(p: dict, obs: Tensor, act: Tensor, nobs: Tensor) -> Tensor:
    tx, tz = nobs[..., IDP_TIP[0]], nobs[..., IDP_TIP[1]]
    alive = p["healthy_reward"] * (tz > p["min_tip_height"]).to(nobs.dtype)
    dist = p["dist_x_weight"] * tx.square() + (tz - p["target_height"]).square()
    vel = p["vel_weights"][0] * nobs[..., 6].square() + p["vel_weights"][1] * nobs[..., 7].square()
    return alive - dist - vel


def _reacher_reward(p: dict, obs: Tensor, act: Tensor, nobs: Tensor) -> Tensor:
    dist = (nobs[..., 8].square() + nobs[..., 9].square() + p["fingertip_target_dz"] ** 2).sqrt()
    return -p["reward_dist_weight"] * dist - _ctrl_cost(p["reward_control_weight"], act)


def _hopper_healthy(p: dict, nobs: Tensor) -> Tensor:
    # is_healthy: qpos[1:3] = (z, pitch); state_vector()[2:] = (qpos[2:], qvel) = next_obs[2:] except that the
    # obs clips qvel at +-10, so |qvel| > 100 (never seen) is missed.
    lo, hi = p["healthy_state_range"]
    state_ok = ((nobs[..., 2:] > lo) & (nobs[..., 2:] < hi)).all(-1)
    return state_ok & _z_angle_ok(p, nobs)


def _z_angle_ok(p: dict, nobs: Tensor) -> Tensor:
    (zlo, zhi), (alo, ahi) = p["healthy_z_range"], p["healthy_angle_range"]
    z, angle = nobs[..., 1], nobs[..., 2]
    return (z > zlo) & (z < zhi) & (angle > alo) & (angle < ahi)


def _ant_healthy(p: dict, nobs: Tensor) -> Tensor:
    zlo, zhi = p["healthy_z_range"]
    z = nobs[..., 2]
    return torch.isfinite(nobs[..., : ANT_NQ + ANT_NV]).all(-1) & (z >= zlo) & (z <= zhi)


def _humanoid_healthy(p: dict, nobs: Tensor) -> Tensor:
    zlo, zhi = p["healthy_z_range"]
    z = nobs[..., 2]
    return (z > zlo) & (z < zhi)


HEALTHY: dict[str, Callable[[dict, Tensor], Tensor]] = {
    "hopper": _hopper_healthy,
    "walker2d": _z_angle_ok,
    "ant": _ant_healthy,
    "humanoid": _humanoid_healthy,
}


def _unhealthy_terminated(p: dict, obs: Tensor, act: Tensor, nobs: Tensor) -> Tensor:
    if not p["terminate_when_unhealthy"]:
        return _never(p, obs, act, nobs)
    return ~HEALTHY[p["family"]](p, nobs)


def _locomotion_reward(p: dict, obs: Tensor, act: Tensor, nobs: Tensor) -> Tensor:
    """forward_weight * (x' - x) / dt + healthy_reward * healthy - ctrl_cost [- contact_cost].

    x is the root x (planar envs), Ant's appended main-body x or Humanoid's appended mass-centre x.
    """
    xi = p["x_index"]
    r = p["forward_reward_weight"] * (nobs[..., xi] - obs[..., xi]) / p["dt"] - _ctrl_cost(p["ctrl_cost_weight"], act)
    if p["family"] in HEALTHY:
        r = r + p["healthy_reward"] * HEALTHY[p["family"]](p, nobs).to(r.dtype)
    if p["family"] == "ant":  # the obs holds the clipped forces; cfrc_ext[0] (world) is always 0
        r = r - p["contact_cost_weight"] * nobs[..., ANT_CFRC[0] : ANT_CFRC[1]].square().sum(-1)
    elif p["family"] == "humanoid":  # the obs holds the raw forces cfrc_ext[1:]; the cost is clipped
        lo, hi = p["contact_cost_range"]
        cost = p["contact_cost_weight"] * nobs[..., HUM_CFRC[0] : HUM_CFRC[1]].square().sum(-1)
        r = r - cost.clamp(min=float(lo), max=float(hi))
    return r


# --------------------------------------------------------------------------- builders

#: canonical name -> gymnasium id, in catalogue order
GYM_IDS = {
    "invertedpendulum": "InvertedPendulum-v5",
    "inverteddoublependulum": "InvertedDoublePendulum-v5",
    "reacher": "Reacher-v5",
    "hopper": "Hopper-v5",
    "walker2d": "Walker2d-v5",
    "halfcheetah": "HalfCheetah-v5",
    "ant": "Ant-v5",
    "humanoid": "Humanoid-v5",
}


def catalogue_key(name: str) -> str | None:
    """The catalogue env ``name`` spells (case, ``_``, ``-``, spaces and a ``-v5`` suffix ignored), else None."""
    key = re.sub(r"[^a-z0-9]", "", name.lower())
    key = re.sub(r"v5$", "", key) if key not in GYM_IDS else key
    return key if key in GYM_IDS else None


LAYOUTS: dict[str, Callable[[], ObsLayout]] = {
    "invertedpendulum": pendulum_layout,
    "inverteddoublependulum": double_pendulum_layout,
    "reacher": reacher_layout,
    "hopper": lambda: planar_layout(PLANAR_JOINTS["hopper"]),
    "walker2d": lambda: planar_layout(PLANAR_JOINTS["walker2d"]),
    "halfcheetah": lambda: planar_layout(PLANAR_JOINTS["halfcheetah"]),
    "ant": ant_layout,
    "humanoid": humanoid_layout,
}
REWARD_ERROR = {
    "invertedpendulum": "exact",
    "inverteddoublependulum": (
        "exact (tip from the appended site position) except that the velocity penalty 0.001 v1^2 + 0.005 v2^2 "
        "uses the unclipped qvel while the obs clips it at +-10: error = 0.001 (v1^2 - 100)_+ + 0.005 (v2^2 - 100)_+ "
        "on the rare steps where a hinge spins faster than 10 rad/s; termination exact"
    ),
    "reacher": "exact",
    "hopper": (
        "exact; termination misses the healthy_state_range check on |qvel| > 100 (the obs clips qvel "
        "at +-10), never seen in practice"
    ),
    "walker2d": "exact",
    "halfcheetah": "exact",
    "ant": "exact (forward reward from the appended main-body x, contact cost from the clipped forces in the obs)",
    "humanoid": "exact (forward reward from the appended mass-centre x, contact cost from cfrc_ext in the obs)",
}
#: Constructor kwargs that change the observation layout: not supported.
LAYOUT_KWARGS = frozenset(
    {
        "xml_file",
        "exclude_current_positions_from_observation",
        "include_cfrc_ext_in_observation",
        "include_cinert_in_observation",
        "include_cvel_in_observation",
        "include_qfrc_actuator_in_observation",
    }
)


def _idp_tip_site(env: Any) -> np.ndarray:
    return env.data.site_xpos[0][[0, 2]].copy()


def _ant_main_body_x(main_body: int | str, env: Any) -> np.ndarray:
    return np.array([env.data.body(main_body).xpos[0]])


def _humanoid_mass_centre_x(env: Any) -> np.ndarray:
    from gymnasium.envs.mujoco.humanoid_v5 import mass_center

    return mass_center(env.model, env.data)[:1]


def build(name: str, overrides: dict[str, Any]) -> EnvSpec:
    """Build the spec of canonical ``name`` with env constructor ``overrides``."""
    gym_id = GYM_IDS[name]
    ctor = env_constructor_params(gym_id)
    bad = sorted(set(overrides) & LAYOUT_KWARGS)
    if bad:
        raise ValueError(f"{name}: {bad} change the observation layout and are not supported")
    unknown = sorted(set(overrides) - set(ctor))
    if unknown:
        accepted = sorted(set(ctor) - LAYOUT_KWARGS)
        raise ValueError(
            f"{name}: unknown env kwargs {unknown}; accepted: {accepted} "
            f"(render/limit kwargs such as render_mode go to spec.make())"
        )
    env_kwargs = dict(overrides)
    if "exclude_current_positions_from_observation" in ctor:
        env_kwargs["exclude_current_positions_from_observation"] = False

    env = gymnasium_make(gym_id, **env_kwargs)
    u = env.unwrapped
    p: Any = {"family": name, "dt": float(u.dt)}
    wrap = None
    if name == "invertedpendulum":
        p["max_abs_angle"] = 0.2  # hard-coded in InvertedPendulumEnv.step
        reward, term = _ip_reward, _ip_terminated
    elif name == "inverteddoublependulum":
        # hard-coded in InvertedDoublePendulumEnv.step/_get_rew
        p.update(
            healthy_reward=float(u._healthy_reward),
            min_tip_height=1.0,
            target_height=2.0,
            dist_x_weight=0.01,
            vel_weights=(0.001, 0.005),
        )
        wrap = partial(AppendObservation, extra=_idp_tip_site, names=("tip_x", "tip_z"))
        reward, term = _idp_reward, _idp_terminated
    elif name == "reacher":
        env.reset(seed=0)
        dz = u.get_body_com("fingertip")[2] - u.get_body_com("target")[2]
        p.update(
            reward_dist_weight=float(u._reward_dist_weight),
            reward_control_weight=float(u._reward_control_weight),
            fingertip_target_dz=float(dz),
        )
        reward, term = _reacher_reward, _never
    else:
        p.update(
            forward_reward_weight=float(u._forward_reward_weight),
            ctrl_cost_weight=float(u._ctrl_cost_weight),
            x_index=0,
        )
        if name != "halfcheetah":
            p.update(
                healthy_reward=float(u._healthy_reward),
                terminate_when_unhealthy=bool(u._terminate_when_unhealthy),
                healthy_z_range=tuple(float(v) for v in u._healthy_z_range),
            )
        if name in ("hopper", "walker2d"):
            p["healthy_angle_range"] = tuple(float(v) for v in u._healthy_angle_range)
        if name == "hopper":
            p["healthy_state_range"] = tuple(float(v) for v in u._healthy_state_range)
        if name == "ant":
            p.update(
                contact_cost_weight=float(u._contact_cost_weight),
                contact_force_range=tuple(float(v) for v in u._contact_force_range),
                x_index=ANT_XREF,
            )
            wrap = partial(AppendObservation, extra=partial(_ant_main_body_x, u._main_body), names=("main_body_x",))
        if name == "humanoid":
            p.update(
                contact_cost_weight=float(u._contact_cost_weight),
                contact_cost_range=tuple(float(v) for v in u._contact_cost_range),
                x_index=HUM_COMX,
            )
            wrap = partial(AppendObservation, extra=_humanoid_mass_centre_x, names=("mass_centre_x",))
        reward = _locomotion_reward
        term = _never if name == "halfcheetah" else _unhealthy_terminated

    p = ReadOnlyDict(p)  # what the reward functions see: read-only
    spec = EnvSpec(
        name=name,
        gym_id=gym_id,
        layout=LAYOUTS[name](),
        act_dim=int(env.action_space.shape[0]),
        action_low=tuple(float(v) for v in env.action_space.low),
        action_high=tuple(float(v) for v in env.action_space.high),
        dt=float(u.dt),
        episode_length=int(gymnasium.spec(gym_id).max_episode_steps),
        params=p,
        env_kwargs=env_kwargs,
        reward_error=REWARD_ERROR[name],
        reward_fn=partial(reward, p),
        terminated_fn=partial(term, p),
        wrap=wrap,
    )
    wrapped_dim = (wrap(env) if wrap is not None else env).observation_space.shape[0]
    env.close()
    if wrapped_dim != spec.obs_dim:
        raise RuntimeError(f"{name}: layout has obs_dim {spec.obs_dim} but the env gives {wrapped_dim}")
    return spec
