"""The GEM dynamics head: predict Lie-algebra coefficients, move group states by the exponential map.

Encoding (observation -> group state), one element per group of the env's ``ObsLayout``:

  - ``Rn``          translation x (the raw coordinates);
  - ``SO2_angle``   rotation R(theta) from the hinge angle theta;
  - ``SO2_cossin``  rotation [[c, -s], [s, c]] from the observed (cos, sin) pair;
  - ``SO3_quat``    rotation from the (w, x, y, z) quaternion, normalised to unit length first (what MuJoCo
                    does with a free joint's quaternion; it matters only right after ``reset``, whose noise
                    leaves the quaternion non-unit, since every ``mj_step`` renormalises it);

plus the velocities and the ``other`` coordinates as plain vectors. The layout's ``derived`` entries (contact
forces and the like, not state) are neither inputs nor targets; ``next_obs`` copies them from the current obs.

Targets, one slot per "unit" (an Rn coordinate, a velocity, an ``other`` entry or a rotation group), units in the
order of their first observation index, rotation groups contributing their tangent dimensions (1 for SO(2),
3 for SO(3)) at that place:

  - Rn, velocity, other:  next - current (invariant Rn coordinates included: rewards read them);
  - SO(2):                alpha = log(R_t^T R_{t+1}), the wrapped angle difference in (-pi, pi]: for a hinge angle
                          ``lie.wrap_angle(d)`` = d - 2 pi ceil(d / 2 pi - 1/2) with d = theta' - theta, for a
                          (cos, sin) pair atan2(c s' - s c', c c' + s s');
  - SO(3):                ``compose="right"``: alpha = log(R_t^T R_{t+1}) (body frame: G' = G exp(alpha), MuJoCo's
                          free-joint convention); ``compose="left"``: alpha = log(R_{t+1} R_t^T) (world frame:
                          G' = exp(alpha) G, the paper's notation); computed on quaternions with
                          ``lie.SO3.quat_log`` of q_t^* q_{t+1} (right) or q_{t+1} q_t^* (left), |alpha| <= pi.

For layouts whose groups are all ``Rn`` or ``SO2_angle`` (the planar envs) the target slots are exactly the
observation indices, so the targets equal ``DeltaHead``'s ``next_obs - obs`` up to the 2 pi wrap of angles.

Decoding (``next_obs``) maps every target sample through exp, so predicted states stay on their groups:
hinge angles become theta + alpha (never wrapped: MuJoCo hinge positions are unbounded), (cos, sin) pairs are
recomputed from atan2(s, c) + alpha, quaternions become q exp(alpha) (right) or exp(alpha) q (left) by
quaternion multiplication with the unit quaternion exp(alpha) = (cos(|alpha|/2), sin(|alpha|/2) alpha/|alpha|),
with the sign picked so that dot(q', q) >= 0 (continuous with the current quaternion, as MuJoCo's integration
keeps it); everything else is current + delta.

Network inputs, in this fixed order (``input_names`` lists them):
  [ non-invariant Rn coordinates, velocities and other entries, in observation order
  | cos(theta) of the SO2_angle groups | sin(theta) of the SO2_angle groups
  | c of the SO2_cossin groups | s of the SO2_cossin groups
  | the 9 rotation-matrix entries (row-major) of each SO3_quat group (sign-free, unlike the quaternion)
  | action ].
Invariant coordinates never enter. For an Rn-only layout this is exactly ``DeltaHead``'s input.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from dynamics.heads import DynamicsHead
from dynamics.losses import gaussian_nll
from envs.layout import ObsLayout
from gem_head.lie import SO2, SO3, wrap_angle

__all__ = ["GemHead", "COMPOSE_MODES", "LOSSES", "wrap_angle"]

COMPOSE_MODES = ("right", "left")
LOSSES = ("nll", "frobenius", "nll+frobenius")


def _apply_right(mul: Callable[[Tensor, Tensor], Tensor], g: Tensor, e: Tensor) -> Tensor:
    """G' = G e (body frame) under the product ``mul``; e = G^-1 G' is _apply_right(mul, G^-1, G')."""
    return mul(g, e)


def _apply_left(mul: Callable[[Tensor, Tensor], Tensor], g: Tensor, e: Tensor) -> Tensor:
    """G' = e G (world frame) under the product ``mul``; e = G' G^-1 is _apply_left(mul, G^-1, G')."""
    return mul(e, g)


#: compose mode -> how a step e moves a group element G (the relative motion of G -> G' is apply(mul, G^-1, G')).
_APPLY = {"right": _apply_right, "left": _apply_left}

#: Target slots per unit kind: one per additive coordinate ("add"), the tangent dimension for a rotation group.
_TANGENT_DIM = {"add": 1, "SO2_angle": SO2.dim, "SO2_cossin": SO2.dim, "SO3_quat": SO3.dim}


def _quat_conj(q: Tensor) -> Tensor:
    """q^* = (w, -x, -y, -z): the inverse of a unit quaternion."""
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


Sel = slice | Tensor


def _sel(indices: list[int]) -> Sel:
    """A basic slice when ``indices`` is a non-empty ascending run (a view, no gather), else a long tensor."""
    if indices and indices == list(range(indices[0], indices[0] + len(indices))):
        return slice(indices[0], indices[0] + len(indices))
    return torch.tensor(indices, dtype=torch.long)


def _take(x: Tensor, sel: Sel) -> Tensor:
    """x[..., sel] along the last dim, contiguous (elementwise kernels on strided views are ~10x slower on CPU)."""
    return x[..., sel].contiguous() if isinstance(sel, slice) else x.index_select(-1, sel)


def _put(out: Tensor, sel: Sel, value: Tensor) -> None:
    """out[..., sel] = value along the last dim (in place)."""
    if isinstance(sel, slice):
        out[..., sel] = value
    else:
        out.index_copy_(-1, sel, value.to(out.dtype))


@dataclass(frozen=True)
class _Indices:
    """Last-dim selections of one device: slices where contiguous, long tensors otherwise."""

    pass_obs: Sel  # obs entries passed to the network unchanged (non-invariant Rn, velocities, other)
    ang_obs: Sel  # SO2_angle obs entries ...
    ang_tgt: Sel  # ... and their target slots
    cs_c: Sel  # cos entries of the SO2_cossin groups ...
    cs_s: Sel  # ... their sin entries ...
    cs_tgt: Sel  # ... and their target slots
    so2_tgt: Sel  # target slots of all SO(2) groups: angles first, then (cos, sin) pairs
    q_obs: Sel  # (w, x, y, z) obs entries of the SO3_quat groups, 4 per group ...
    q_tgt: Sel  # ... and their target slots, 3 per group
    sq_tgt: Sel  # target slots scored by squared error in the Frobenius loss (Rn, velocities, other)
    carry: Sel  # derived obs entries: not predicted, copied from the current observation

    def to(self, device: torch.device) -> _Indices:
        return _Indices(**{k: v if isinstance(v, slice) else v.to(device) for k, v in self.__dict__.items()})


class GemHead(DynamicsHead):
    """GEM head: targets are Lie-algebra coefficients per group (+ deltas); next state = exp(alpha) composed with G.

    Args:
      layout: the env's observation layout (``envs.get(name).layout``).
      act_dim: action dimension.
      compose: ``"right"`` (G' = G exp(alpha), body frame, default) or ``"left"`` (G' = exp(alpha) G).
        Only SO(3) groups differ; SO(2) and Rn commute.
      loss: ``"nll"`` (Gaussian NLL of the targets), ``"frobenius"`` (the paper's algebraic loss, see
        ``frobenius_loss``; the log-variance is fitted by NLL with the mean detached, since PETS samples from it)
        or ``"nll+frobenius"`` (NLL + ``frobenius_weight`` * Frobenius).
      frobenius_weight: weight of the Frobenius term in ``"nll+frobenius"`` (finite, >= 0).
    """

    name = "gem"

    def __init__(
        self,
        layout: ObsLayout,
        act_dim: int,
        *,
        compose: str = "right",
        loss: str = "nll",
        frobenius_weight: float = 1.0,
    ) -> None:
        if not isinstance(layout, ObsLayout):
            raise ValueError(f"GemHead needs an envs.layout.ObsLayout, got {type(layout).__name__}")
        if not isinstance(act_dim, int) or isinstance(act_dim, bool) or act_dim < 1:
            raise ValueError(f"act_dim must be a positive int, got {act_dim!r}")
        if compose not in COMPOSE_MODES:
            raise ValueError(
                f"compose must be one of {COMPOSE_MODES} ('right': G' = G exp(alpha), body frame; "
                f"'left': G' = exp(alpha) G), got {compose!r}"
            )
        if loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
        if (
            isinstance(frobenius_weight, bool)
            or not isinstance(frobenius_weight, (int, float))
            or not math.isfinite(frobenius_weight)
            or frobenius_weight < 0
        ):
            raise ValueError(f"frobenius_weight must be a finite number >= 0, got {frobenius_weight!r}")
        super().__init__(layout, act_dim)
        self.compose = compose
        self._apply = _APPLY[compose]  # bound once: the hot paths never compare strings
        self.loss_kind = loss
        self.frobenius_weight = float(frobenius_weight)

        # Units: (first obs index, kind, obs indices, label); kind "add" (one Rn coordinate, velocity or other entry)
        # or the layout kind of a rotation group; a unit takes _TANGENT_DIM[kind] target slots.
        units: list[tuple[int, str, tuple[int, ...], str]] = []
        for g in layout.groups:
            if g.kind == "Rn":
                units += [(i, "add", (i,), f"{g.name}[{k}]") for k, i in enumerate(g.indices)]
            else:
                units.append((min(g.indices), g.kind, g.indices, g.name))
        units += [(i, "add", (i,), f"vel[{i}]") for i in layout.velocities]
        units += [(i, "add", (i,), f"other[{i}]") for i in layout.other]
        units.sort(key=lambda u: u[0])

        obs_of: dict[str, list[int]] = {kind: [] for kind in _TANGENT_DIM}  # obs indices per kind, in unit order
        tgt_of: dict[str, list[int]] = {kind: [] for kind in _TANGENT_DIM}  # target slots per kind, in unit order
        target_names: list[str] = []
        dynamic_obs = set(layout.velocities) | set(layout.other)
        group_slots: list[int] = []
        t = 0
        for _, kind, idx, label in units:
            slots = list(range(t, t + _TANGENT_DIM[kind]))
            if kind != "add" or idx[0] not in dynamic_obs:
                group_slots += slots
            obs_of[kind] += idx
            tgt_of[kind] += slots
            if kind == "add":
                target_names.append(f"d {label}")
            elif len(slots) == 1:
                target_names.append(f"alpha {label}")
            else:
                target_names += [f"alpha {label}[{a}]" for a in "xyz"]
            t += len(slots)
        sq_tgt = tgt_of["add"]  # scored by squared error in the Frobenius loss
        ang_obs, ang_tgt = obs_of["SO2_angle"], tgt_of["SO2_angle"]
        cs_c, cs_s, cs_tgt = obs_of["SO2_cossin"][0::2], obs_of["SO2_cossin"][1::2], tgt_of["SO2_cossin"]
        q_obs, q_tgt = obs_of["SO3_quat"], tgt_of["SO3_quat"]
        # (obs index, target index) of the additive slots (hinge angles included), in target order.
        add_pairs = sorted(zip(obs_of["add"] + ang_obs, sq_tgt + ang_tgt), key=lambda p: p[1])
        self.target_dim = t
        self.target_names: tuple[str, ...] = tuple(target_names)
        #: Target slots of the group ("static") part: Rn coordinates and rotation coefficients, ascending.
        self.group_slots: tuple[int, ...] = tuple(group_slots)
        #: Target slots of the velocities and ``other`` entries (the "dynamic" part), ascending.
        self.velocity_slots: tuple[int, ...] = tuple(sorted(set(range(t)) - set(group_slots)))

        # Contiguous runs (obs start, target start, length) of the additive slots: next = obs + target there.
        self._segments: list[tuple[int, int, int]] = []
        for o, tt in add_pairs:
            if (
                self._segments
                and self._segments[-1][0] + self._segments[-1][2] == o
                and self._segments[-1][1] + self._segments[-1][2] == tt
            ):
                so, st, ln = self._segments[-1]
                self._segments[-1] = (so, st, ln + 1)
            else:
                self._segments.append((o, tt, 1))
        self._pure_additive = self._segments == [(0, 0, layout.obs_dim)] and not cs_tgt and not q_tgt
        self.num_quat = len(q_obs) // 4

        # Inputs: pass-through (non-invariant Rn, velocities, other) in obs order, then the group features.
        pass_obs = sorted(set(obs_of["add"]) - set(layout.invariant))
        names = [f"obs[{i}]" for i in pass_obs]
        names += [f"cos obs[{i}]" for i in ang_obs] + [f"sin obs[{i}]" for i in ang_obs]
        names += [f"obs[{i}] (cos)" for i in cs_c] + [f"obs[{i}] (sin)" for i in cs_s]
        for k in range(self.num_quat):
            names += [f"R{r}{c} of obs[{q_obs[4 * k]}:{q_obs[4 * k] + 4}]" for r in range(3) for c in range(3)]
        names += [f"act[{j}]" for j in range(act_dim)]
        self.input_names: tuple[str, ...] = tuple(names)
        self.input_dim = len(names)

        self._n_ang, self._n_cs, self._n_sq, self._n_carry = len(ang_obs), len(cs_c), len(sq_tgt), len(layout.derived)
        self._n_so2 = self._n_ang + self._n_cs
        self._cpu = _Indices(
            pass_obs=_sel(pass_obs),
            ang_obs=_sel(ang_obs),
            ang_tgt=_sel(ang_tgt),
            cs_c=_sel(cs_c),
            cs_s=_sel(cs_s),
            cs_tgt=_sel(cs_tgt),
            so2_tgt=_sel(ang_tgt + cs_tgt),
            q_obs=_sel(q_obs),
            q_tgt=_sel(q_tgt),
            sq_tgt=_sel(sq_tgt),
            carry=_sel(list(layout.derived)),
        )
        self._by_device: dict[torch.device, _Indices] = {torch.device("cpu"): self._cpu}

    def target_slots_of(self, group: str) -> tuple[int, ...]:
        """Target slots of the layout's group ``group``: one per coordinate of an Rn group (in its order), the
        tangent coordinates of a rotation group."""
        g = self.layout.group(group)
        if g.kind == "Rn":
            return tuple(self.target_names.index(f"d {g.name}[{k}]") for k in range(len(g.indices)))
        label = f"alpha {g.name}"
        return tuple(i for i, n in enumerate(self.target_names) if n == label or n.startswith(label + "["))

    def __repr__(self) -> str:
        return (
            f"GemHead(obs_dim={self.obs_dim}, act_dim={self.act_dim}, input_dim={self.input_dim}, "
            f"target_dim={self.target_dim}, compose={self.compose!r}, loss={self.loss_kind!r})"
        )

    # ------------------------------------------------------------------ helpers
    def _idx(self, device: torch.device) -> _Indices:
        """The index selections on ``device`` (moved once, then cached)."""
        got = self._by_device.get(device)
        if got is None:
            got = self._by_device[device] = self._cpu.to(device)
        return got

    def _check(self, where: str, **tensors: tuple[Tensor, int]) -> None:
        for label, (x, dim) in tensors.items():
            if not isinstance(x, Tensor) or not x.is_floating_point():
                got = x.dtype if isinstance(x, Tensor) else type(x).__name__
                raise ValueError(f"GemHead.{where}: {label} must be a floating-point tensor, got {got}")
            if x.dim() < 1 or x.shape[-1] != dim:
                raise ValueError(f"GemHead.{where}: {label} must have shape (..., {dim}), got {tuple(x.shape)}")

    def _unit_quat(self, obs: Tensor, ix: _Indices) -> Tensor:
        """Quaternions (..., Q, 4) of the SO3 groups, normalised (the rotation the observation encodes)."""
        q = _take(obs, ix.q_obs).unflatten(-1, (self.num_quat, 4))
        return q * torch.rsqrt((q * q).sum(-1, keepdim=True))

    def _so2_cos_sin(self, obs: Tensor, ix: _Indices) -> tuple[Tensor, Tensor]:
        """(cos, sin) (..., K) of all SO(2) groups, hinge angles first, then (cos, sin) pairs (``so2_tgt`` order)."""
        ang = _take(obs, ix.ang_obs)
        c = torch.cat([torch.cos(ang), _take(obs, ix.cs_c)], dim=-1)
        s = torch.cat([torch.sin(ang), _take(obs, ix.cs_s)], dim=-1)
        return c, s

    def group_matrices(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        """Rotation matrices of the observation: SO(2) (..., K, 2, 2) in ``so2`` target order, SO(3) (..., Q, 3, 3)."""
        self._check("group_matrices", obs=(obs, self.obs_dim))
        ix = self._idx(obs.device)
        so2 = SO2.from_cos_sin(*self._so2_cos_sin(obs, ix))
        so3 = SO3.from_quat(self._unit_quat(obs, ix)) if self.num_quat else obs.new_zeros(*obs.shape[:-1], 0, 3, 3)
        return so2, so3

    # ------------------------------------------------------------------ the three maps
    def inputs(self, obs: Tensor, act: Tensor) -> Tensor:
        """Network inputs (..., input_dim) in the order of ``input_names`` (invariant coordinates excluded)."""
        self._check("inputs", obs=(obs, self.obs_dim), act=(act, self.act_dim))
        ix = self._idx(obs.device)
        parts = [obs[..., ix.pass_obs] if isinstance(ix.pass_obs, slice) else obs.index_select(-1, ix.pass_obs)]
        if self._n_ang:
            ang = _take(obs, ix.ang_obs)
            parts += [torch.cos(ang), torch.sin(ang)]
        if self._n_cs:
            parts += [_take(obs, ix.cs_c), _take(obs, ix.cs_s)]
        if self.num_quat:
            parts.append(SO3.from_quat(_take(obs, ix.q_obs).unflatten(-1, (self.num_quat, 4))).flatten(-3))
        parts.append(act)
        return torch.cat(parts, dim=-1)

    def targets(self, obs: Tensor, next_obs: Tensor) -> Tensor:
        """Targets (..., target_dim): algebra coefficients of the relative motion per group, deltas elsewhere."""
        self._check("targets", obs=(obs, self.obs_dim), next_obs=(next_obs, self.obs_dim))
        if self._pure_additive and not self._n_ang:
            return next_obs - obs
        ix = self._idx(obs.device)
        batch = torch.broadcast_shapes(obs.shape[:-1], next_obs.shape[:-1])
        obs, next_obs = obs.expand(*batch, self.obs_dim), next_obs.expand(*batch, self.obs_dim)
        out = obs.new_empty(*batch, self.target_dim, dtype=torch.promote_types(obs.dtype, next_obs.dtype))
        for o, t, n in self._segments:
            torch.sub(next_obs[..., o : o + n], obs[..., o : o + n], out=out[..., t : t + n])
        if self._n_ang:
            _put(out, ix.ang_tgt, wrap_angle(_take(out, ix.ang_tgt)))
        if self._n_cs:
            c, s = _take(obs, ix.cs_c), _take(obs, ix.cs_s)
            c2, s2 = _take(next_obs, ix.cs_c), _take(next_obs, ix.cs_s)
            _put(out, ix.cs_tgt, torch.atan2(c * s2 - s * c2, c * c2 + s * s2))
        if self.num_quat:
            q0, q1 = self._unit_quat(obs, ix), self._unit_quat(next_obs, ix)
            rel = self._apply(SO3.quat_mul, _quat_conj(q0), q1)  # q0^* q1 (right) or q1 q0^* (left)
            _put(out, ix.q_tgt, SO3.quat_log(rel).flatten(-2))
        return out

    def next_obs(self, obs: Tensor, target: Tensor) -> Tensor:
        """Next observation (..., obs_dim): exp of the target applied to each group, current + delta elsewhere."""
        self._check("next_obs", obs=(obs, self.obs_dim), target=(target, self.target_dim))
        if self._pure_additive:
            return obs + target
        ix = self._idx(obs.device)
        batch = torch.broadcast_shapes(obs.shape[:-1], target.shape[:-1])
        obs, target = obs.expand(*batch, self.obs_dim), target.expand(*batch, self.target_dim)
        out = obs.new_empty(*batch, self.obs_dim, dtype=torch.promote_types(obs.dtype, target.dtype))
        for o, t, n in self._segments:
            torch.add(obs[..., o : o + n], target[..., t : t + n], out=out[..., o : o + n])
        if self._n_cs:
            theta = torch.atan2(_take(obs, ix.cs_s), _take(obs, ix.cs_c)) + _take(target, ix.cs_tgt)
            _put(out, ix.cs_c, torch.cos(theta))
            _put(out, ix.cs_s, torch.sin(theta))
        if self.num_quat:
            q = self._unit_quat(obs, ix)
            e = SO3.quat_exp(_take(target, ix.q_tgt).unflatten(-1, (self.num_quat, 3)))
            qn = self._apply(SO3.quat_mul, q, e)
            qn = torch.where((qn * q).sum(-1, keepdim=True) < 0, -qn, qn)
            _put(out, ix.q_obs, qn.flatten(-2))
        if self._n_carry:
            _put(out, ix.carry, _take(obs, ix.carry))
        return out

    # ------------------------------------------------------------------ losses
    def frobenius_loss(
        self, mean: Tensor, target: Tensor, obs: Tensor, next_obs: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        """The paper's algebraic loss (Algorithm 1), per member: (E,) for (E, B, .) inputs.

        Per sample: [ sum over SO(2)/SO(3) groups of ||exp(alpha_hat) o G_t - G_{t+1}||_F^2 (2x2 / 3x3 matrices,
        o = this head's composition, G from ``obs`` and ``next_obs``) + sum of squared errors (mean - target)^2 of
        the Rn, velocity and other slots ] / target_dim, averaged over all leading dims but the first. For a
        rotation error of angle phi a group term is ||R1 - R2||_F^2 = 8 sin^2(phi / 2) ~ 2 phi^2 (SO(2), SO(3)).
        With ``scale`` (target_dim,) (the model's target std) every term is in standardised units: a squared
        error is divided by its slot's scale^2, a group term by the mean scale^2 of the group's slots.
        """
        self._check(
            "frobenius_loss",
            mean=(mean, self.target_dim),
            target=(target, self.target_dim),
            obs=(obs, self.obs_dim),
            next_obs=(next_obs, self.obs_dim),
        )
        if mean.dim() < 2:
            raise ValueError(f"GemHead.frobenius_loss expects (E, B, .) batches, got mean of shape {tuple(mean.shape)}")
        ix = self._idx(mean.device)
        inv_var = None if scale is None else scale.to(mean).reciprocal().square()
        per = mean.new_zeros(mean.shape[:-1])
        if self._n_sq:
            sq = (_take(mean, ix.sq_tgt) - _take(target, ix.sq_tgt)).square()
            per = per + (sq if inv_var is None else sq * _take(inv_var, ix.sq_tgt)).sum(-1)
        if self._n_so2:
            g0 = SO2.from_cos_sin(*self._so2_cos_sin(obs, ix))
            g1 = SO2.from_cos_sin(*self._so2_cos_sin(next_obs, ix))
            pred = SO2.compose(SO2.exp(_take(mean, ix.so2_tgt).unsqueeze(-1)), g0)
            sq = (pred - g1).square().sum((-1, -2))
            per = per + (sq if inv_var is None else sq * _take(inv_var, ix.so2_tgt)).sum(-1)
        if self.num_quat:
            g0, g1 = SO3.from_quat(self._unit_quat(obs, ix)), SO3.from_quat(self._unit_quat(next_obs, ix))
            step = SO3.exp(_take(mean, ix.q_tgt).unflatten(-1, (self.num_quat, 3)))
            pred = self._apply(SO3.compose, g0, step)
            sq = (pred - g1).square().sum((-1, -2))
            if inv_var is not None:
                sq = sq * _take(inv_var, ix.q_tgt).unflatten(-1, (self.num_quat, 3)).mean(-1)
            per = per + sq.sum(-1)
        return (per / self.target_dim).flatten(1).mean(dim=1)

    def loss(
        self, mean: Tensor, logvar: Tensor, target: Tensor, obs: Tensor, next_obs: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        """Per-member training loss (E,) for (E, B, .) batches, by ``self.loss_kind`` (``scale``: see
        ``frobenius_loss``; the NLL does not need it):

        - ``nll``: gaussian_nll(mean, logvar, target) in the algebra coordinates;
        - ``frobenius``: frobenius_loss(mean) + gaussian_nll(mean.detach(), logvar, target): the mean is fitted by
          the algebraic loss only, the log-variance (which PETS samples from) by the NLL around that fixed mean;
        - ``nll+frobenius``: gaussian_nll(mean, logvar, target) + frobenius_weight * frobenius_loss(mean).
        """
        self._check(
            "loss",
            mean=(mean, self.target_dim),
            logvar=(logvar, self.target_dim),
            target=(target, self.target_dim),
            obs=(obs, self.obs_dim),
            next_obs=(next_obs, self.obs_dim),
        )
        if mean.dim() < 2:
            raise ValueError(f"GemHead.loss expects (E, B, .) batches, got mean of shape {tuple(mean.shape)}")
        if self.loss_kind == "nll":
            return gaussian_nll(mean, logvar, target)
        frob = self.frobenius_loss(mean, target, obs, next_obs, scale)
        if self.loss_kind == "frobenius":
            return frob + gaussian_nll(mean.detach(), logvar, target)
        return gaussian_nll(mean, logvar, target) + self.frobenius_weight * frob
