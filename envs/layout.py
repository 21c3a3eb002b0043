"""Observation layouts: which observation indices form which Lie group, which are velocities.

A layout is the single source of truth that both dynamics heads read:
the delta head uses it to drop position-invariant coordinates from the network
inputs; the GEM head uses it to encode an observation into group elements and
to decode predicted group elements back into an observation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

GroupKind = Literal["Rn", "SO2_angle", "SO2_cossin", "SO3_quat"]

#: Number of observation entries each group kind occupies (None: any n >= 1); ``gem_head.codecs.register_codec``
#: adds the kinds of new codecs.
KIND_WIDTH: dict[str, int | None] = {"Rn": None, "SO2_angle": 1, "SO2_cossin": 2, "SO3_quat": 4}


def _cossin_qpos(x: Any) -> Any:
    """The hinge angle ``atan2(sin, cos)`` of ``(..., 2)`` cos/sin entries, as ``(..., 1)``."""
    import numpy as np

    return np.arctan2(x[..., 1], x[..., 0])[..., None]


def _quat_qpos(q: Any) -> Any:
    """The quaternion ``(..., 4)`` normalised (MuJoCo's free and ball joints expect unit quaternions)."""
    import numpy as np

    return q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)


#: How a group kind's observation entries give MuJoCo ``qpos`` coordinates (numpy), where they are not the entries
#: themselves (Rn coordinates, SO2_angle radians): the one place of that conversion (``envs.render``).
KIND_QPOS: dict[str, Callable[[Any], Any]] = {"SO2_cossin": _cossin_qpos, "SO3_quat": _quat_qpos}


@dataclass(frozen=True)
class Group:
    """One group-valued part of the observation.

    kind:
      - ``Rn``: translations; ``indices`` are the n coordinates.
      - ``SO2_angle``: a hinge angle in radians; ``indices == (i,)``.
      - ``SO2_cossin``: a hinge angle given as ``(cos_index, sin_index)``.
      - ``SO3_quat``: an orientation as a unit quaternion, ``indices == (w, x, y, z)``.
    """

    name: str
    kind: GroupKind
    indices: tuple[int, ...]

    def __post_init__(self) -> None:
        if self.kind not in KIND_WIDTH:
            raise ValueError(
                f"group {self.name!r}: unknown kind {self.kind!r}; accepted: {sorted(KIND_WIDTH)} (a kind of your own "
                "is known once the module that calls gem_head.codecs.register_codec is imported: import it in the "
                "module that builds this layout, or name it in the config key imports, e.g. imports=[my_codec]; "
                "docs/models.md)"
            )
        width = KIND_WIDTH[self.kind]
        if width is None and len(self.indices) < 1 or width is not None and len(self.indices) != width:
            raise ValueError(
                f"group {self.name!r} of kind {self.kind} has {len(self.indices)} indices, expected {width or '>= 1'}"
            )


@dataclass(frozen=True)
class ObsLayout:
    """Index-by-index description of an observation vector.

    Every index in ``range(obs_dim)`` belongs to exactly one of: a group, ``velocities``,
    ``other`` or ``derived``. ``invariant`` lists the group (Rn) coordinates the dynamics do not
    depend on (root x, and y for Ant/Humanoid): they are never network inputs.

    ``derived`` entries are quantities MuJoCo computes from the state (contact forces, body inertias
    and velocities, actuator forces): not part of the Markov state, never network inputs, never
    predicted; a predicted next observation carries them over from the current one (docs/envs.md).
    ``other`` entries (constraint forces, appended reward positions) are predicted like velocities.

    ``root`` names the floating base as ``(translation group, rotation group)``: an ``Rn`` group of 2 coordinates
    with an ``SO2_angle`` (a planar root: x, z and the pitch about y) or of 3 with an ``SO3_quat`` (a free joint);
    ``None`` where the body has no floating base. The ``gem-se`` model composes these two as one SE(2) / SE(3)
    element (``gem_head.se_root``); every other model reads the groups as usual.
    """

    obs_dim: int
    groups: tuple[Group, ...]
    velocities: tuple[int, ...] = ()
    other: tuple[int, ...] = ()
    invariant: tuple[int, ...] = field(default=())
    derived: tuple[int, ...] = ()
    root: tuple[str, str] | None = None

    def __post_init__(self) -> None:
        seen = [i for g in self.groups for i in g.indices] + [*self.velocities, *self.other, *self.derived]
        if sorted(seen) != list(range(self.obs_dim)):
            dup = sorted({i for i in seen if seen.count(i) > 1})
            missing = sorted(set(range(self.obs_dim)) - set(seen))
            extra = sorted(set(seen) - set(range(self.obs_dim)))
            raise ValueError(
                f"layout does not cover 0..{self.obs_dim - 1} exactly once: "
                f"duplicated {dup}, missing {missing}, out of range {extra}"
            )
        rn = {i for g in self.groups if g.kind == "Rn" for i in g.indices}
        if not set(self.invariant) <= rn:
            raise ValueError(f"invariant indices {sorted(set(self.invariant) - rn)} are not Rn group coordinates")
        if self.root is not None:
            by_name = {g.name: g for g in self.groups}
            trans, rot = (by_name.get(name) for name in self.root)
            ok = trans is not None and rot is not None and trans.kind == "Rn"
            if not (ok and (rot.kind, len(trans.indices)) in (("SO2_angle", 2), ("SO3_quat", 3))):
                raise ValueError(
                    f"root {self.root!r} must name an Rn group of 2 coordinates and an SO2_angle group (planar) or an "
                    "Rn group of 3 and an SO3_quat group (free joint)"
                )

    @property
    def model_indices(self) -> tuple[int, ...]:
        """Observation indices a model may see (all but the invariant and derived ones), in order."""
        skip = set(self.invariant) | set(self.derived)
        return tuple(i for i in range(self.obs_dim) if i not in skip)

    @property
    def predicted_indices(self) -> tuple[int, ...]:
        """Observation indices a model predicts (all but the derived ones), in order."""
        skip = set(self.derived)
        return tuple(i for i in range(self.obs_dim) if i not in skip)

    def group(self, name: str) -> Group:
        """The group called ``name`` (KeyError naming the groups there are, if none is)."""
        for g in self.groups:
            if g.name == name:
                return g
        raise KeyError(f"no group {name!r}; the layout has {[g.name for g in self.groups]}")

    def groups_of(self, kind: GroupKind) -> tuple[Group, ...]:
        return tuple(g for g in self.groups if g.kind == kind)
