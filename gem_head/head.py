"""The GEM dynamics head: predict Lie-algebra coefficients, move group states by the exponential map.

The head is a loop over group codecs (``gem_head.codecs``), one per group kind present in the env's ``ObsLayout``,
each owning its kind's encoding, target, decoding and Frobenius term (the formulas are in each codec's docstring):

  - ``Rn``          translations and every plain entry (velocities, ``other``): x' = x + d;
  - ``SO2_angle``   a hinge angle theta: alpha = wrap(theta' - theta), theta' = theta + alpha (never wrapped);
  - ``SO2_cossin``  an observed (cos, sin) pair: alpha = atan2(c s' - s c', c c' + s s');
  - ``SO3_quat``    a (w, x, y, z) quaternion, normalised first: alpha = log(R_t^T R_{t+1}) (right) or
                    log(R_{t+1} R_t^T) (left), q' = q exp(alpha) or exp(alpha) q;

and, for ``gem-se`` (``gem_head.se_root``), a root codec (``SE2`` / ``SE3``) that composes the root's translation
with its rotation in the body frame. The layout's ``derived`` entries (contact forces and the like, not state)
are neither inputs nor targets; ``next_obs`` copies them from the current obs.

Targets, one slot per "unit" (an Rn coordinate, a velocity, an ``other`` entry or a rotation group), units in the
order of their first observation index, rotation groups contributing their tangent dimensions (1 for SO(2),
3 for SO(3)) at that place. For layouts whose groups are all ``Rn`` or ``SO2_angle`` (the planar envs) the target
slots are exactly the observation indices, so the targets equal ``DeltaHead``'s ``next_obs - obs`` up to the
2 pi wrap of angles.

Decoding (``next_obs``) maps every target sample through exp, so predicted states stay on their groups.

Network inputs: the codecs' features, codec by codec in the order of ``codecs.CODECS`` (the order the kinds were
registered), then the action (``input_names`` lists them):
  [ non-invariant Rn coordinates, velocities and other entries, in observation order
  | cos(theta) of the SO2_angle groups | sin(theta) of the SO2_angle groups
  | c of the SO2_cossin groups | s of the SO2_cossin groups
  | the 9 rotation-matrix entries (row-major) of each SO3_quat group (sign-free, unlike the quaternion)
  | action ].
Invariant coordinates never enter. For an Rn-only layout this is exactly ``DeltaHead``'s input.

The additive codecs (``Rn``, ``SO2_angle``) share one step: ``next - obs`` (targets) and ``obs + target``
(decoding) over contiguous runs of their slots, before each codec's own fix-up (the angle wrap); every index
selection is prepared once per device, so no map has a per-sample or per-group Python loop.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dynamics.heads import DynamicsHead
from dynamics.losses import gaussian_nll
from envs.layout import ObsLayout
from gem_head.codecs import CODECS, GroupCodec, put, sel, take
from gem_head.lie import wrap_angle

__all__ = ["GemHead", "COMPOSE_MODES", "LOSSES", "wrap_angle"]

COMPOSE_MODES = ("right", "left")
LOSSES = ("nll", "frobenius", "nll+frobenius")

#: A unit of the layout: (first obs index, kind, obs indices, label).
Unit = tuple[int, str, tuple[int, ...], str]


def layout_units(layout: ObsLayout) -> list[Unit]:
    """The layout's units in observation order: each group split by its codec, velocities and other entries as Rn."""
    units: list[Unit] = []
    for g in layout.groups:
        if g.kind not in CODECS:
            raise ValueError(f"group {g.name!r}: no codec for kind {g.kind!r}; registered: {sorted(CODECS)}")
        units += [(min(idx), g.kind, idx, label) for idx, label in CODECS[g.kind].units(g)]
    units += [(i, "Rn", (i,), f"vel[{i}]") for i in layout.velocities]
    units += [(i, "Rn", (i,), f"other[{i}]") for i in layout.other]
    return sorted(units, key=lambda u: u[0])


def additive_segments(codecs: list[GroupCodec]) -> list[tuple[int, int, int]]:
    """Contiguous runs (obs start, target start, length) of the additive codecs' slots, in target order."""
    pairs = sorted(((o, t) for c in codecs if c.additive for o, t in zip(c.obs, c.slots)), key=lambda p: p[1])
    segments: list[tuple[int, int, int]] = []
    for o, t in pairs:
        if segments and segments[-1][0] + segments[-1][2] == o and segments[-1][1] + segments[-1][2] == t:
            so, st, ln = segments[-1]
            segments[-1] = (so, st, ln + 1)
        else:
            segments.append((o, t, 1))
    return segments


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
    #: Compose the layout's root with a root codec (``gem_head.se_root``): ``gem-se``.
    compose_root = False

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
        self.loss_kind = loss
        self.frobenius_weight = float(frobenius_weight)
        self._build(layout_units(layout))

    def _build(self, units: list[Unit]) -> None:
        """Target slots and names of the units, one codec per kind present, inputs, the additive runs."""
        obs_of: dict[str, list[int]] = {kind: [] for kind in CODECS}  # obs indices per kind, in unit order
        tgt_of: dict[str, list[int]] = {kind: [] for kind in CODECS}  # target slots per kind, in unit order
        target_names: list[str] = []
        dynamic_obs = set(self.layout.velocities) | set(self.layout.other)
        group_slots: list[int] = []
        t = 0
        for _, kind, idx, label in units:
            slots = list(range(t, t + CODECS[kind].tangent_dim))
            if kind != "Rn" or idx[0] not in dynamic_obs:
                group_slots += slots
            obs_of[kind] += idx
            tgt_of[kind] += slots
            target_names += CODECS[kind].slot_names(label)
            t += len(slots)
        self.target_dim = t
        self.target_names: tuple[str, ...] = tuple(target_names)
        #: Target slots of the group ("static") part: Rn coordinates and rotation coefficients, ascending.
        self.group_slots: tuple[int, ...] = tuple(group_slots)
        #: Target slots of the velocities and ``other`` entries (the "dynamic" part), ascending.
        self.velocity_slots: tuple[int, ...] = tuple(sorted(set(range(t)) - set(group_slots)))

        #: The codecs, in input order (root codec last): every map loops over them.
        self.codecs: tuple[GroupCodec, ...] = tuple(
            CODECS[kind](obs_of[kind], tgt_of[kind], self.layout, self.compose) for kind in CODECS if tgt_of[kind]
        )
        if self.compose_root:
            self.codecs += (self._root_codec(),)
        self._segments = additive_segments(list(self.codecs))
        self._pure_additive = self._segments == [(0, 0, self.layout.obs_dim)] and all(c.additive for c in self.codecs)
        self._plain_delta = self._pure_additive and all(c.plain_delta for c in self.codecs)
        names = [n for c in self.codecs for n in c.input_names()] + [f"act[{j}]" for j in range(self.act_dim)]
        self.input_names: tuple[str, ...] = tuple(names)
        self.input_dim = len(names)
        self._n_carry = len(self.layout.derived)
        self._carry = sel(list(self.layout.derived))
        self._by_device: dict[torch.device, tuple[tuple[GroupCodec, ...], slice | Tensor]] = {
            torch.device("cpu"): (self.codecs, self._carry)
        }

    def _root_codec(self) -> GroupCodec:
        """The codec composing the layout's root (``compose_root``): the registered ``composite`` codec whose
        rotation kind and translation size match, built on the root's translation then rotation slots."""
        trans, rot = (self.layout.group(name) for name in self.layout.root)
        for cls in CODECS.values():
            if getattr(cls, "composite", False) and (cls.rotation_kind, cls.translation_dim) == (
                rot.kind,
                len(trans.indices),
            ):
                obs = [*trans.indices, *rot.indices]
                slots = [*self.target_slots_of(trans.name), *self.target_slots_of(rot.name)]
                return cls(obs, slots, self.layout, self.compose)
        raise ValueError(f"no root codec for a root of {len(trans.indices)} coordinates and a {rot.kind} rotation")

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
    def _on(self, device: torch.device) -> tuple[tuple[GroupCodec, ...], slice | Tensor]:
        """The codecs and the derived-entry selection on ``device`` (moved once, then cached)."""
        got = self._by_device.get(device)
        if got is None:
            moved = tuple(c.to(device) for c in self.codecs)
            carry = self._carry if isinstance(self._carry, slice) else self._carry.to(device)
            got = self._by_device[device] = (moved, carry)
        return got

    def _codecs_on(self, device: torch.device) -> tuple[GroupCodec, ...]:
        return self._on(device)[0]

    def _check(self, where: str, **tensors: tuple[Tensor, int]) -> None:
        for label, (x, dim) in tensors.items():
            if not isinstance(x, Tensor) or not x.is_floating_point():
                got = x.dtype if isinstance(x, Tensor) else type(x).__name__
                raise ValueError(f"GemHead.{where}: {label} must be a floating-point tensor, got {got}")
            if x.dim() < 1 or x.shape[-1] != dim:
                raise ValueError(f"GemHead.{where}: {label} must have shape (..., {dim}), got {tuple(x.shape)}")

    def group_matrices(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        """Rotation matrices of the observation: SO(2) (..., K, 2, 2) in target order, SO(3) (..., Q, 3, 3)."""
        self._check("group_matrices", obs=(obs, self.obs_dim))
        out = []
        for size in (2, 3):
            mats = [c.matrices(obs) for c in self._codecs_on(obs.device) if c.matrix_size == size]
            mats = [m for m in mats if m is not None]
            out.append(torch.cat(mats, dim=-3) if mats else obs.new_zeros(*obs.shape[:-1], 0, size, size))
        return out[0], out[1]

    # ------------------------------------------------------------------ the three maps
    def inputs(self, obs: Tensor, act: Tensor) -> Tensor:
        """Network inputs (..., input_dim) in the order of ``input_names`` (invariant coordinates excluded)."""
        self._check("inputs", obs=(obs, self.obs_dim), act=(act, self.act_dim))
        parts = [x for c in self._codecs_on(obs.device) for x in c.inputs(obs)]
        parts.append(act)
        return torch.cat(parts, dim=-1)

    def targets(self, obs: Tensor, next_obs: Tensor) -> Tensor:
        """Targets (..., target_dim): algebra coefficients of the relative motion per group, deltas elsewhere."""
        self._check("targets", obs=(obs, self.obs_dim), next_obs=(next_obs, self.obs_dim))
        if self._plain_delta:
            return next_obs - obs
        batch = torch.broadcast_shapes(obs.shape[:-1], next_obs.shape[:-1])
        obs, next_obs = obs.expand(*batch, self.obs_dim), next_obs.expand(*batch, self.obs_dim)
        out = obs.new_empty(*batch, self.target_dim, dtype=torch.promote_types(obs.dtype, next_obs.dtype))
        for o, t, n in self._segments:
            torch.sub(next_obs[..., o : o + n], obs[..., o : o + n], out=out[..., t : t + n])
        for codec in self._codecs_on(obs.device):
            codec.target(obs, next_obs, out)
        return out

    def next_obs(self, obs: Tensor, target: Tensor) -> Tensor:
        """Next observation (..., obs_dim): exp of the target applied to each group, current + delta elsewhere."""
        self._check("next_obs", obs=(obs, self.obs_dim), target=(target, self.target_dim))
        if self._pure_additive:
            return obs + target
        codecs, carry = self._on(obs.device)
        batch = torch.broadcast_shapes(obs.shape[:-1], target.shape[:-1])
        obs, target = obs.expand(*batch, self.obs_dim), target.expand(*batch, self.target_dim)
        out = obs.new_empty(*batch, self.obs_dim, dtype=torch.promote_types(obs.dtype, target.dtype))
        for o, t, n in self._segments:
            torch.add(obs[..., o : o + n], target[..., t : t + n], out=out[..., o : o + n])
        for codec in codecs:
            codec.decode(obs, target, out)
        if self._n_carry:
            put(out, carry, take(obs, carry))
        return out

    # ------------------------------------------------------------------ losses
    def frobenius_loss(
        self, mean: Tensor, target: Tensor, obs: Tensor, next_obs: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        """The paper's algebraic loss (Algorithm 1), per member: (E,) for (E, B, .) inputs.

        Per sample: [ sum over the codecs of their terms (``codecs``): ||exp(alpha_hat) o G_t - G_{t+1}||_F^2 per
        SO(2)/SO(3) group (2x2 / 3x3 matrices, o = this head's composition, G from ``obs`` and ``next_obs``), the
        squared errors (mean - target)^2 of the Rn, velocity and other slots ] / target_dim, averaged over all
        leading dims but the first. For a rotation error of angle phi a group term is ||R1 - R2||_F^2
        = 8 sin^2(phi / 2) ~ 2 phi^2 (SO(2), SO(3)). With ``scale`` (target_dim,) (the model's target std) every
        term is in standardised units: a squared error is divided by its slot's scale^2, a group term by the
        mean scale^2 of the group's slots.
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
        inv_var = None if scale is None else scale.to(mean).reciprocal().square()
        per = mean.new_zeros(mean.shape[:-1])
        for codec in self._codecs_on(mean.device):
            term = codec.frobenius(mean, target, obs, next_obs, inv_var)
            if term is not None:
                per = per + term
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
