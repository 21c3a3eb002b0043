"""``gem-se``: GEM with the floating root as one rigid-body element, moved by a body-frame twist.

``GemHead`` composes a floating root as independent pieces: its translation in R^n (targets ``p' - p`` in the world
frame) and its rotation on SO(2) or SO(3). ``GemSEHead`` composes the two together, on SE(2) for a planar root
(x, z and the pitch about y: Hopper, Walker2d, HalfCheetah) or SE(3) for a free joint (Ant, Humanoid), as the
right (body-frame) action ``G' = G exp(xi)``, ``xi = (omega, u)``, through a root codec (``SE2`` / ``SE3`` in
``gem_head.codecs.CODECS``) that runs after the group codecs:

- rotation ``omega``: the rotation codec's right-composed target (``log(R^T R')``; for the pitch the wrapped
  angle difference);
- translation ``u = V(omega)^-1 R^T (p' - p)`` in the root's translation slots, where ``R`` is the root's rotation
  and ``V`` the left Jacobian of SO(2) / SO(3) (``gem_head.lie.SE2.v_inv_apply`` / ``SE3.v_inv_apply``). Decoding
  inverts it exactly: ``p' = p + R V(omega) u``.

So the target is the displacement seen from the body: a step along the body's own axis is the same target
whatever the body's heading, pitch or position (tests/test_gem_se.py checks that the targets do not change when
the world is moved by any rigid motion). In the x-z plane MuJoCo's pitch ``theta`` (a hinge about +y) rotates the
body by ``R(-theta)``, so the planar SE(2) angle is ``-theta`` (checked against MuJoCo's body frame in the tests).

Everything else is ``GemHead``'s: the network inputs (the root codec adds none: the root x, and y, still never
enter), the other groups, the velocities, the losses (the root codec adds no Frobenius term: the root's ``u``
slots are scored like the other additive slots). Only the body-frame composition is defined: ``compose`` must be
``"right"``.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor

from envs.layout import ObsLayout
from gem_head.codecs import GroupCodec, register_codec
from gem_head.head import GemHead
from gem_head.lie import SE2, SE3, SO3, LieGroup

__all__ = ["GemSEHead", "SE2RootCodec", "SE3RootCodec", "check_gem_se"]


class _RootCodec(GroupCodec):
    """A root codec: the layout's root translation p (``translation_dim`` entries) and rotation R as one SE(n)
    element, right action G' = G exp(omega, u): target u = V(omega)^-1 R^T (p' - p), decoding p' = p + R V(omega) u,
    omega being the rotation codec's target. Built on (translation, rotation) obs indices and target slots."""

    composite: ClassVar[bool] = True
    rotation_kind: ClassVar[str]
    translation_dim: ClassVar[int]
    group: ClassVar[type[LieGroup]]

    def __init__(self, obs: list[int], slots: list[int], layout: ObsLayout, compose: str) -> None:
        super().__init__(obs, slots, layout, compose)
        n = self.translation_dim
        self._p_obs, self._r_obs = self.obs[:n], self.obs[n:]
        self._p_tgt, self._w_tgt = self.slots[:n], self.slots[n:]

    def rotation(self, obs: Tensor) -> Tensor:
        """The root's rotation R as a matrix (..., n, n)."""
        raise NotImplementedError

    def omega(self, target: Tensor) -> Tensor:
        """The root's rotation coefficients in the group's convention."""
        raise NotImplementedError

    def target(self, obs: Tensor, next_obs: Tensor, out: Tensor) -> None:
        dp = out[..., self._p_tgt]  # p' - p in the world frame (the additive step)
        local = (self.rotation(obs).transpose(-1, -2) @ dp.unsqueeze(-1)).squeeze(-1)
        out[..., self._p_tgt] = self.group.v_inv_apply(self.omega(out), local)

    def decode(self, obs: Tensor, target: Tensor, out: Tensor) -> None:
        step = self.group.v_apply(self.omega(target), target[..., self._p_tgt])  # in the body frame
        world = (self.rotation(obs) @ step.unsqueeze(-1)).squeeze(-1)
        out[..., self._p_obs] = obs[..., self._p_obs] + world.to(out.dtype)


@register_codec
class SE2RootCodec(_RootCodec):
    """SE(2) root of the x-z plane: p = (x, z), R = R(-theta) for MuJoCo's pitch theta (a hinge about +y),
    omega = -alpha_pitch; u = V(omega)^-1 R^T (p' - p), p' = p + R V(omega) u with
    V(omega) = [[A, -B], [B, A]], A = sin(omega)/omega, B = (1 - cos omega)/omega (``SE2.v_apply``)."""

    kind, width, tangent_dim = "SE2", None, SE2.dim
    rotation_kind, translation_dim, group = "SO2_angle", 2, SE2

    def rotation(self, obs: Tensor) -> Tensor:
        phi = -obs[..., self._r_obs[0]]
        c, s = torch.cos(phi), torch.sin(phi)
        return torch.stack([c, -s, s, c], dim=-1).unflatten(-1, (2, 2))

    def omega(self, target: Tensor) -> Tensor:
        return -target[..., self._w_tgt][..., 0]


@register_codec
class SE3RootCodec(_RootCodec):
    """SE(3) root of a free joint: p = (x, y, z), R = R(q / |q|), omega = the quaternion's body-frame alpha;
    u = V(omega)^-1 R^T (p' - p), p' = p + R V(omega) u with V = I + B hat(w) + C hat(w)^2,
    B = (1 - cos t)/t^2, C = (t - sin t)/t^3, t = |w| (``SE3.v_apply``)."""

    kind, width, tangent_dim = "SE3", None, SE3.dim
    rotation_kind, translation_dim, group = "SO3_quat", 3, SE3

    def rotation(self, obs: Tensor) -> Tensor:
        q = obs[..., self._r_obs]
        return SO3.from_quat(q * torch.rsqrt((q * q).sum(-1, keepdim=True)))

    def omega(self, target: Tensor) -> Tensor:
        return target[..., self._w_tgt]


def check_gem_se(layout: ObsLayout, compose: str, env: str = "this env's layout") -> None:
    """The one check of what gem-se needs (the model, the config and the API all call it): a layout with a floating
    ``root`` and the body-frame composition; a one-line ValueError otherwise, naming ``env``."""
    if layout.root is None:
        import envs

        with_root = [name for name in envs.names() if envs.get(name).layout.root is not None]
        raise ValueError(
            f"--model gem-se composes a floating root on SE(2)/SE(3) and {env} has none; it applies to "
            f"{', '.join(with_root)} (use gem elsewhere)"
        )
    if compose != "right":
        raise ValueError(
            f"--model gem-se composes the root in the body frame: gem.compose must be right, got {compose!r}"
        )


class GemSEHead(GemHead):
    """GEM with the layout's ``root`` as one SE(2) / SE(3) element composed in the body frame (module docstring).

    Args: as :class:`gem_head.head.GemHead`; the layout must have a ``root``, and ``compose`` must be ``"right"``.
    """

    name = "gem-se"
    compose_root = True

    def __init__(
        self,
        layout: ObsLayout,
        act_dim: int,
        *,
        compose: str = "right",
        loss: str = "nll",
        frobenius_weight: float = 1.0,
    ) -> None:
        if isinstance(layout, ObsLayout):
            check_gem_se(layout, compose)
        super().__init__(layout, act_dim, compose=compose, loss=loss, frobenius_weight=frobenius_weight)
        self.root_codec: _RootCodec = self.codecs[-1]
        self.planar = isinstance(self.root_codec, SE2RootCodec)

    def __repr__(self) -> str:
        return super().__repr__().replace("GemHead(", "GemSEHead(", 1)
