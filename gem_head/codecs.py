"""Group codecs of the GEM head: one class per group kind, each owning its kind's part of the head's maps.

A codec of kind K holds every unit of kind K in the layout at once (a unit is one coordinate of an ``Rn`` group,
a velocity, an ``other`` entry, or one whole rotation group), as index selections prepared once, so every map
below is a handful of batched tensor ops whatever the number of units. Per codec:

  - ``inputs``: the network features of its units (``input_names`` names them);
  - ``target``: its target slots, the log of the relative motion G_t^-1 G_{t+1} (right) or G_{t+1} G_t^-1 (left);
  - ``decode``: its observation entries of the next state, exp of its target slots composed with G_t;
  - ``frobenius``: its per-sample term of the paper's algebraic loss (``GemHead.frobenius_loss``);
  - ``matrices``: its group elements as matrices, where it has some; class methods, on one group's entries, the
    evaluation's metrics (``step_terms``, ``rotation_angle``, ``entry_difference``).

``additive`` codecs (``Rn``, ``SO2_angle``), whose group product adds the observed coordinates, get ``next - obs``
in their slots (``obs + target`` in their entries) at once, in contiguous runs, before their fix-ups run.

``CODECS`` maps a kind to its codec class, in the order the kinds' features enter the network; a new kind is one
``GroupCodec`` subclass and one ``register_codec`` call; ``gem-se``'s root codecs live in ``gem_head.se_root``.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import ClassVar

import torch
from torch import Tensor

from envs.layout import KIND_WIDTH, Group, ObsLayout
from gem_head.indexing import put, sel, take
from gem_head.lie import SO2, SO3, wrap_angle

__all__ = [
    "CODECS",
    "GroupCodec",
    "RnCodec",
    "SO2Codec",
    "SO2AngleCodec",
    "SO2CosSinCodec",
    "SO3QuatCodec",
    "register_codec",
    "unregister_codec",
    "sel",
    "take",
    "put",
]


def apply_right(mul: Callable[[Tensor, Tensor], Tensor], g: Tensor, e: Tensor) -> Tensor:
    """G' = G e (body frame) under the product ``mul``; e = G^-1 G' is apply_right(mul, G^-1, G')."""
    return mul(g, e)


def apply_left(mul: Callable[[Tensor, Tensor], Tensor], g: Tensor, e: Tensor) -> Tensor:
    """G' = e G (world frame) under the product ``mul``; e = G' G^-1 is apply_left(mul, G^-1, G')."""
    return mul(e, g)


#: compose mode -> how a step e moves a group element G (the relative motion of G -> G' is apply(mul, G^-1, G')).
APPLY = {"right": apply_right, "left": apply_left}


class GroupCodec:
    """One group kind's encoding, target, decoding and Frobenius term, for all its units of a layout.

    Args:
      obs: observation indices of the units, concatenated in unit order (``width`` per unit; 1 for ``Rn``).
      slots: target slots of the units, concatenated in unit order (``tangent_dim`` per unit).
      layout: the env's layout; compose: ``"right"`` or ``"left"`` (see ``GemHead``).

    Subclasses set the class attributes and override the maps they need; the defaults contribute nothing.
    """

    kind: ClassVar[str]
    #: Observation entries per group of this kind (None: any n, one unit per entry).
    width: ClassVar[int | None]
    #: Target slots per unit.
    tangent_dim: ClassVar[int]
    #: The head writes next - obs into the slots / obs + target into the entries (one slot per entry) first.
    additive: ClassVar[bool] = False
    #: ``target`` adds nothing to next - obs (with ``additive``: the target is the plain difference).
    plain_delta: ClassVar[bool] = False
    #: Side of the matrices ``matrices`` returns (None: no matrices).
    matrix_size: ClassVar[int | None] = None
    #: A rotation: its entries get the rotation error (:meth:`rotation_angle`), not the translation error.
    is_rotation: ClassVar[bool] = False
    #: Order of :meth:`step_terms` in the step error's sum: the metric's since v1 (0 plain, 1 angles, 2 quaternions).
    step_place: ClassVar[int] = 0

    @classmethod
    def step_terms(cls, pred: Tensor, true: Tensor) -> Tensor:
        """The squared terms ``(..., t)`` one group ``(..., width)`` adds to the step error: ``(x - x')^2``."""
        return (pred - true).pow(2)

    @classmethod
    def rotation_angle(cls, pred: Tensor, true: Tensor) -> Tensor:
        """Geodesic angle ``(...)`` in [0, pi] between predicted and true entries ``(..., width)`` of a rotation."""
        raise NotImplementedError(f"{cls.kind} is not a rotation kind")

    @classmethod
    def entry_difference(cls, pred: Tensor, true: Tensor) -> Tensor:
        """Group-aware ``pred - true`` of one group's entries ``(..., width)`` (plain unless the kind says)."""
        return pred - true

    def __init__(self, obs: list[int], slots: list[int], layout: ObsLayout, compose: str) -> None:
        self.obs, self.slots, self.layout = list(obs), list(slots), layout
        self.num_units = len(slots) // self.tangent_dim
        self._apply = APPLY[compose]  # bound once: the hot paths never compare strings
        self.tgt = sel(self.slots)

    @classmethod
    def units(cls, group: Group) -> list[tuple[tuple[int, ...], str]]:
        """(observation indices, label) of each unit of ``group``: the whole group by default."""
        return [(group.indices, group.name)]

    @classmethod
    def slot_names(cls, label: str) -> list[str]:
        """Names of one unit's target slots: ``alpha LABEL`` (one slot) or ``alpha LABEL[x]`` ..."""
        if cls.tangent_dim == 1:
            return [f"alpha {label}"]
        axes = "xyz" if cls.tangent_dim == 3 else [str(a) for a in range(cls.tangent_dim)]
        return [f"alpha {label}[{a}]" for a in axes]

    def to(self, device: torch.device) -> GroupCodec:
        """A copy whose index tensors live on ``device``."""
        moved = copy.copy(self)
        for key, value in vars(self).items():
            if isinstance(value, Tensor):
                setattr(moved, key, value.to(device))
        return moved

    def input_names(self) -> list[str]:
        """Names of the features ``inputs`` returns, in order."""
        return []

    def inputs(self, obs: Tensor) -> list[Tensor]:
        """Network features (..., k) of the units, in ``input_names`` order."""
        return []

    def target(self, obs: Tensor, next_obs: Tensor, out: Tensor) -> None:
        """Write the units' targets into ``out[..., slots]`` (additive: it already holds next - obs)."""

    def decode(self, obs: Tensor, target: Tensor, out: Tensor) -> None:
        """Write the units' next entries into ``out[..., obs]`` (additive: it already holds obs + target)."""

    def frobenius(
        self, mean: Tensor, target: Tensor, obs: Tensor, next_obs: Tensor, inv_var: Tensor | None
    ) -> Tensor | None:
        """Per-sample Frobenius term (...) of the units (``inv_var``: 1 / scale^2 per slot), or None."""
        return None

    def matrices(self, obs: Tensor) -> Tensor | None:
        """Group elements as matrices (..., units, n, n), or None for non-matrix kinds."""
        return None


class RnCodec(GroupCodec):
    """R^n: translations, and every plain vector entry (velocities, ``other``); one unit per coordinate.

    Encoding x (the coordinates; the layout's invariant ones never enter the network); target d = x' - x
    (log and exp are the identity, composition is addition, left = right); decoding x' = x + d; Frobenius term
    sum_i (d_hat_i - d_i)^2 / scale_i^2 (the algebra of R^n is R^n: the squared error).
    """

    kind, width, tangent_dim, additive, plain_delta = "Rn", None, 1, True, True

    def __init__(self, obs: list[int], slots: list[int], layout: ObsLayout, compose: str) -> None:
        super().__init__(obs, slots, layout, compose)
        self.pass_obs = sorted(set(self.obs) - set(layout.invariant))
        self.pass_sel = sel(self.pass_obs)

    @classmethod
    def units(cls, group: Group) -> list[tuple[tuple[int, ...], str]]:
        return [((i,), f"{group.name}[{k}]") for k, i in enumerate(group.indices)]

    @classmethod
    def slot_names(cls, label: str) -> list[str]:
        return [f"d {label}"]

    def input_names(self) -> list[str]:
        return [f"obs[{i}]" for i in self.pass_obs]

    def inputs(self, obs: Tensor) -> list[Tensor]:
        s = self.pass_sel
        return [obs[..., s] if isinstance(s, slice) else obs.index_select(-1, s)]

    def frobenius(
        self, mean: Tensor, target: Tensor, obs: Tensor, next_obs: Tensor, inv_var: Tensor | None
    ) -> Tensor | None:
        sq = (take(mean, self.tgt) - take(target, self.tgt)).square()
        return (sq if inv_var is None else sq * take(inv_var, self.tgt)).sum(-1)


class SO2Codec(GroupCodec):
    """Shared part of the SO(2) kinds: G = R(theta) from ``cos_sin``, tangent dim 1 (the angle); SO(2) commutes,
    so left = right. Frobenius term sum_k ||R(alpha_hat_k) R_t - R_{t+1}||_F^2 / scale_k^2
    (= 8 sin^2(phi / 2) ~ 2 phi^2 for a rotation error phi)."""

    tangent_dim, matrix_size = 1, 2

    def cos_sin(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        """(cos theta, sin theta) (..., units) of the observation's rotations."""
        raise NotImplementedError

    def matrices(self, obs: Tensor) -> Tensor:
        return SO2.from_cos_sin(*self.cos_sin(obs))

    def frobenius(
        self, mean: Tensor, target: Tensor, obs: Tensor, next_obs: Tensor, inv_var: Tensor | None
    ) -> Tensor | None:
        g0, g1 = self.matrices(obs), self.matrices(next_obs)
        pred = SO2.compose(SO2.exp(take(mean, self.tgt).unsqueeze(-1)), g0)
        sq = (pred - g1).square().sum((-1, -2))
        return (sq if inv_var is None else sq * take(inv_var, self.tgt)).sum(-1)


class SO2AngleCodec(SO2Codec):
    """SO(2) from a hinge angle theta (one entry): G = R(theta), inputs (cos theta, sin theta).

    Target alpha = log(R_t^T R_{t+1}) = ``wrap_angle(theta' - theta)`` = d - 2 pi ceil(d / 2 pi - 1/2), in
    (-pi, pi]; decoding theta' = theta + alpha, never wrapped (MuJoCo hinge positions are unbounded).
    """

    kind, width, additive, is_rotation, step_place = "SO2_angle", 1, True, True, 1

    @classmethod
    def rotation_angle(cls, pred: Tensor, true: Tensor) -> Tensor:
        """``|wrap(a - a')|``."""
        return wrap_angle(pred[..., 0] - true[..., 0]).abs()

    @classmethod
    def step_terms(cls, pred: Tensor, true: Tensor) -> Tensor:
        """``wrap(a - a')^2``."""
        return wrap_angle(pred - true).pow(2)

    @classmethod
    def entry_difference(cls, pred: Tensor, true: Tensor) -> Tensor:
        """The angle difference wrapped to (-pi, pi]."""
        return wrap_angle(pred - true)

    def __init__(self, obs: list[int], slots: list[int], layout: ObsLayout, compose: str) -> None:
        super().__init__(obs, slots, layout, compose)
        self.ang = sel(self.obs)

    def input_names(self) -> list[str]:
        return [f"cos obs[{i}]" for i in self.obs] + [f"sin obs[{i}]" for i in self.obs]

    def inputs(self, obs: Tensor) -> list[Tensor]:
        ang = take(obs, self.ang)
        return [torch.cos(ang), torch.sin(ang)]

    def target(self, obs: Tensor, next_obs: Tensor, out: Tensor) -> None:
        put(out, self.tgt, wrap_angle(take(out, self.tgt)))

    def cos_sin(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        ang = take(obs, self.ang)
        return torch.cos(ang), torch.sin(ang)


class SO2CosSinCodec(SO2Codec):
    """SO(2) from an observed (c, s) = (cos theta, sin theta) pair: G = [[c, -s], [s, c]], inputs (c, s).

    Target alpha = log(R_t^T R_{t+1}) = atan2(c s' - s c', c c' + s s'); decoding recomputes the pair from
    theta' = atan2(s, c) + alpha: (c', s') = (cos theta', sin theta').
    """

    kind, width, is_rotation = "SO2_cossin", 2, True

    @classmethod
    def rotation_angle(cls, pred: Tensor, true: Tensor) -> Tensor:
        """``|wrap(a - a')|`` with ``a = atan2(sin, cos)`` (this normalises the pair); the difference stays plain."""
        return wrap_angle(torch.atan2(pred[..., 1], pred[..., 0]) - torch.atan2(true[..., 1], true[..., 0])).abs()

    def __init__(self, obs: list[int], slots: list[int], layout: ObsLayout, compose: str) -> None:
        super().__init__(obs, slots, layout, compose)
        self.c_obs, self.s_obs = self.obs[0::2], self.obs[1::2]
        self.c, self.s = sel(self.c_obs), sel(self.s_obs)

    def input_names(self) -> list[str]:
        return [f"obs[{i}] (cos)" for i in self.c_obs] + [f"obs[{i}] (sin)" for i in self.s_obs]

    def inputs(self, obs: Tensor) -> list[Tensor]:
        return [take(obs, self.c), take(obs, self.s)]

    def target(self, obs: Tensor, next_obs: Tensor, out: Tensor) -> None:
        c, s = take(obs, self.c), take(obs, self.s)
        c2, s2 = take(next_obs, self.c), take(next_obs, self.s)
        put(out, self.tgt, torch.atan2(c * s2 - s * c2, c * c2 + s * s2))

    def decode(self, obs: Tensor, target: Tensor, out: Tensor) -> None:
        theta = torch.atan2(take(obs, self.s), take(obs, self.c)) + take(target, self.tgt)
        put(out, self.c, torch.cos(theta))
        put(out, self.s, torch.sin(theta))

    def cos_sin(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        return take(obs, self.c), take(obs, self.s)


def unit_quat(q: Tensor) -> Tensor:
    """Quaternions ``(..., 4)`` divided by their norm (a zero quaternion stays zero; inf/NaN give NaN)."""
    return q / q.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny)


def aligned_quat(q: Tensor, q_true: Tensor) -> Tensor:
    """``q`` or ``-q`` (the same rotation), whichever is on ``q_true``'s half of the quaternion sphere."""
    return torch.where((q * q_true).sum(-1, keepdim=True) < 0, -q, q)


def quat_conj(q: Tensor) -> Tensor:
    """q^* = (w, -x, -y, -z): the inverse of a unit quaternion."""
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


class SO3QuatCodec(GroupCodec):
    """SO(3) from a (w, x, y, z) quaternion q, normalised to unit length first (MuJoCo renormalises every step;
    only ``reset`` leaves it non-unit): G = R(q); inputs the 9 entries of R(q), row-major (sign-free, unlike q).

    Target ``compose="right"``: alpha = log(R_t^T R_{t+1}) = quat_log(q_t^* q_{t+1}) (body frame: G' = G exp(alpha),
    MuJoCo's free-joint convention); ``"left"``: alpha = log(R_{t+1} R_t^T) = quat_log(q_{t+1} q_t^*) (world frame:
    G' = exp(alpha) G, the paper's notation); |alpha| <= pi. Decoding q' = q e (right) or e q (left) with the unit
    quaternion e = exp(alpha) = (cos(|alpha|/2), sin(|alpha|/2) alpha/|alpha|), sign picked so that dot(q', q) >= 0
    (continuous with the current quaternion, as MuJoCo's integration keeps it). Frobenius term
    sum_k ||exp(alpha_hat_k) o R_t - R_{t+1}||_F^2 / mean(scale_k^2) (o: this composition).
    """

    kind, width, tangent_dim, matrix_size, is_rotation, step_place = "SO3_quat", 4, 3, 3, True, 2

    @classmethod
    def step_terms(cls, pred: Tensor, true: Tensor) -> Tensor:
        """``min(|q - q'|^2, |q + q'|^2)`` of the quaternions as given (not normalised): ``(..., 1)``."""
        return torch.minimum((pred - true).pow(2).sum(-1, True), (pred + true).pow(2).sum(-1, True))

    @classmethod
    def rotation_angle(cls, pred: Tensor, true: Tensor) -> Tensor:
        """``2 acos |<q, q'>|`` of the normalised quaternions, as ``4 atan2(|q - s q'|, |q + s q'|)`` with
        ``s = sign <q, q'>``, exact near 0 where acos loses half the digits (a zero quaternion: pi)."""
        q_true = unit_quat(true)
        q = aligned_quat(unit_quat(pred), q_true)
        return 4 * torch.atan2((q - q_true).norm(dim=-1), (q + q_true).norm(dim=-1))

    @classmethod
    def entry_difference(cls, pred: Tensor, true: Tensor) -> Tensor:
        """``s q/|q| - q'/|q'|`` with ``s = sign <q, q'>`` (``q`` and ``-q`` are the same rotation)."""
        q_true = unit_quat(true)
        return aligned_quat(unit_quat(pred), q_true) - q_true

    def __init__(self, obs: list[int], slots: list[int], layout: ObsLayout, compose: str) -> None:
        super().__init__(obs, slots, layout, compose)
        self.q = sel(self.obs)

    def input_names(self) -> list[str]:
        q = self.obs
        return [
            f"R{r}{c} of obs[{q[4 * k]}:{q[4 * k] + 4}]"
            for k in range(self.num_units)
            for r in range(3)
            for c in range(3)
        ]

    def unit_quat(self, obs: Tensor) -> Tensor:
        """Quaternions (..., units, 4), normalised (the rotation the observation encodes)."""
        q = take(obs, self.q).unflatten(-1, (self.num_units, 4))
        return q * torch.rsqrt((q * q).sum(-1, keepdim=True))

    def inputs(self, obs: Tensor) -> list[Tensor]:
        return [SO3.from_quat(take(obs, self.q).unflatten(-1, (self.num_units, 4))).flatten(-3)]

    def target(self, obs: Tensor, next_obs: Tensor, out: Tensor) -> None:
        q0, q1 = self.unit_quat(obs), self.unit_quat(next_obs)
        rel = self._apply(SO3.quat_mul, quat_conj(q0), q1)  # q0^* q1 (right) or q1 q0^* (left)
        put(out, self.tgt, SO3.quat_log(rel).flatten(-2))

    def decode(self, obs: Tensor, target: Tensor, out: Tensor) -> None:
        q = self.unit_quat(obs)
        e = SO3.quat_exp(take(target, self.tgt).unflatten(-1, (self.num_units, 3)))
        qn = self._apply(SO3.quat_mul, q, e)
        qn = torch.where((qn * q).sum(-1, keepdim=True) < 0, -qn, qn)
        put(out, self.q, qn.flatten(-2))

    def matrices(self, obs: Tensor) -> Tensor:
        return SO3.from_quat(self.unit_quat(obs))

    def frobenius(
        self, mean: Tensor, target: Tensor, obs: Tensor, next_obs: Tensor, inv_var: Tensor | None
    ) -> Tensor | None:
        g0, g1 = self.matrices(obs), self.matrices(next_obs)
        step = SO3.exp(take(mean, self.tgt).unflatten(-1, (self.num_units, 3)))
        sq = (self._apply(SO3.compose, g0, step) - g1).square().sum((-1, -2))
        if inv_var is not None:
            sq = sq * take(inv_var, self.tgt).unflatten(-1, (self.num_units, 3)).mean(-1)
        return sq.sum(-1)


#: kind name -> codec class, in the order the kinds' features enter the network (``register_codec`` appends).
CODECS: dict[str, type[GroupCodec]] = {}


#: Kinds that ``register_codec`` added to ``envs.layout.KIND_WIDTH`` (``unregister_codec`` removes only those).
_ADDED_KINDS: set[str] = set()


def _check_codec(cls: object) -> None:
    """Refuse, in one line, a class that is not a complete codec: its attributes, and a non-additive kind's maps."""
    if not (isinstance(cls, type) and issubclass(cls, GroupCodec)):
        raise TypeError(f"register_codec takes a subclass of gem_head.codecs.GroupCodec, got {cls!r}")
    kind, width, dim = (getattr(cls, k, None) for k in ("kind", "width", "tangent_dim"))
    if not isinstance(kind, str) or not kind:
        raise ValueError(f"codec {cls.__name__}: set the class attribute kind to its kind's name (a str), got {kind!r}")
    if not (width is None or (isinstance(width, int) and width >= 1)) or "width" not in dir(cls):
        raise ValueError(f"codec {kind!r}: width must be the entries per group (an int >= 1) or None, got {width!r}")
    if not (isinstance(dim, int) and dim >= 1):
        raise ValueError(f"codec {kind!r}: tangent_dim must be the target slots per unit (an int >= 1), got {dim!r}")
    missing = [m for m in ("target", "decode") if getattr(cls, m) is getattr(GroupCodec, m) and not cls.additive]
    base_angle = cls.rotation_angle.__func__ is GroupCodec.rotation_angle.__func__
    missing += ["rotation_angle"] * (cls.is_rotation and base_angle)
    if missing:
        raise ValueError(f"codec {kind!r} must define {' and '.join(missing)} (a kind that is not additive: the base "
                         "class's maps write nothing; with is_rotation: the evaluation's rotation error)")  # fmt: skip


def register_codec(cls: type[GroupCodec]) -> type[GroupCodec]:
    """Add ``cls`` under ``cls.kind`` (a decorator too); ``envs.layout.Group`` accepts it from then on (unless a
    ``composite`` root codec). A kind registered to another class, or of another width in the layout, or a class
    short of a codec's attributes or (not additive) of its ``target`` and ``decode``: an error."""
    _check_codec(cls)
    known = CODECS.get(cls.kind)
    if known is not None and known is not cls:
        raise ValueError(f"codec kind {cls.kind!r} is already registered to {known.__name__}")
    composite = getattr(cls, "composite", False)
    if not composite and cls.kind in KIND_WIDTH and KIND_WIDTH[cls.kind] != cls.width:
        raise ValueError(f"kind {cls.kind!r} has width {KIND_WIDTH[cls.kind]} in envs.layout, {cls.width} in {cls}")
    CODECS[cls.kind] = cls
    if not composite and cls.kind not in KIND_WIDTH:
        KIND_WIDTH[cls.kind] = cls.width
        _ADDED_KINDS.add(cls.kind)
    return cls


def unregister_codec(kind: str) -> None:
    """Remove a kind added by ``register_codec`` (layouts using a kind it added become invalid again)."""
    del CODECS[kind]
    if kind in _ADDED_KINDS:
        _ADDED_KINDS.discard(kind)
        del KIND_WIDTH[kind]


for _cls in (RnCodec, SO2AngleCodec, SO2CosSinCodec, SO3QuatCodec):
    register_codec(_cls)
