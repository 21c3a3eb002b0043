"""``gem-se``: GEM with the floating root as one rigid-body element, moved by a body-frame twist.

``GemHead`` composes a floating root as independent pieces: its translation in R^n (targets ``p' - p`` in the world
frame) and its rotation on SO(2) or SO(3). ``GemSEHead`` composes the two together, on SE(2) for a planar root
(x, z and the pitch about y: Hopper, Walker2d, HalfCheetah) or SE(3) for a free joint (Ant, Humanoid), as the
right (body-frame) action ``G' = G exp(xi)``, ``xi = (omega, u)``:

- rotation ``omega``: the same as ``gem``'s right-composed target (``log(R^T R')``; for the pitch the wrapped
  angle difference);
- translation ``u = V(omega)^-1 R^T (p' - p)`` in the root's target slots, where ``R`` is the root's rotation and
  ``V`` the left Jacobian of SO(2) / SO(3) (``gem_head.lie.SE2.v_inv_apply`` / ``SE3.v_inv_apply``). Decoding
  inverts it exactly: ``p' = p + R V(omega) u``.

So the target is the displacement seen from the body: a step along the body's own axis is the same target
whatever the body's heading, pitch or position (tests/test_gem_se.py checks that the targets do not change when
the world is moved by any rigid motion). In the x-z plane MuJoCo's pitch ``theta`` (a hinge about +y) rotates the
body by ``R(-theta)``, so the planar SE(2) angle is ``-theta`` (checked against MuJoCo's body frame in the tests).

Everything else is ``GemHead``'s: the network inputs (the root x, and y, still never enter), the other groups, the
velocities, the losses (the root's ``u`` slots are scored like the other additive slots by the Frobenius loss).
Only the body-frame composition is defined: ``compose`` must be ``"right"``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from envs.layout import ObsLayout
from gem_head.head import GemHead
from gem_head.lie import SE2, SE3, SO3

__all__ = ["GemSEHead"]


class GemSEHead(GemHead):
    """GEM with the layout's ``root`` as one SE(2) / SE(3) element composed in the body frame (module docstring).

    Args: as :class:`gem_head.head.GemHead`; the layout must have a ``root``, and ``compose`` must be ``"right"``.
    """

    name = "gem-se"

    def __init__(
        self,
        layout: ObsLayout,
        act_dim: int,
        *,
        compose: str = "right",
        loss: str = "nll",
        frobenius_weight: float = 1.0,
    ) -> None:
        if isinstance(layout, ObsLayout) and layout.root is None:
            raise ValueError(
                "gem-se composes a floating root on SE(2) / SE(3): this env's layout has none (a root exists on "
                "hopper, walker2d, halfcheetah, ant and humanoid); use gem"
            )
        if compose != "right":
            raise ValueError(f"gem-se composes the root in the body frame only (gem.compose=right), got {compose!r}")
        super().__init__(layout, act_dim, compose=compose, loss=loss, frobenius_weight=frobenius_weight)
        trans, rot = (layout.group(name) for name in layout.root)
        self.planar = rot.kind == "SO2_angle"
        self._p_obs = list(trans.indices)
        self._r_obs = list(rot.indices)
        self._p_tgt = list(self.target_slots_of(trans.name))
        self._w_tgt = list(self.target_slots_of(rot.name))

    def __repr__(self) -> str:
        return super().__repr__().replace("GemHead(", "GemSEHead(", 1)

    def _root_rotation(self, obs: Tensor) -> Tensor:
        """The root's rotation as a matrix: (..., 2, 2) in the x-z plane (angle -pitch) or (..., 3, 3)."""
        if self.planar:
            phi = -obs[..., self._r_obs[0]]
            c, s = torch.cos(phi), torch.sin(phi)
            return torch.stack([c, -s, s, c], dim=-1).unflatten(-1, (2, 2))
        q = obs[..., self._r_obs]
        return SO3.from_quat(q * torch.rsqrt((q * q).sum(-1, keepdim=True)))

    def _omega(self, target: Tensor) -> Tensor:
        """The root's rotation coefficients in the group's convention: the SE(2) angle (...) or w (..., 3)."""
        w = target[..., self._w_tgt]
        return -w[..., 0] if self.planar else w

    def targets(self, obs: Tensor, next_obs: Tensor) -> Tensor:
        """GemHead's targets with the root's translation slots replaced by ``u = V(omega)^-1 R^T (p' - p)``."""
        out = super().targets(obs, next_obs)
        obs = obs.expand(*out.shape[:-1], self.obs_dim)
        dp = out[..., self._p_tgt]  # p' - p in the world frame
        local = (self._root_rotation(obs).transpose(-1, -2) @ dp.unsqueeze(-1)).squeeze(-1)
        group = SE2 if self.planar else SE3
        out[..., self._p_tgt] = group.v_inv_apply(self._omega(out), local)
        return out

    def next_obs(self, obs: Tensor, target: Tensor) -> Tensor:
        """GemHead's next observation with the root's translation ``p' = p + R V(omega) u``."""
        out = super().next_obs(obs, target)
        batch = out.shape[:-1]
        obs, target = obs.expand(*batch, self.obs_dim), target.expand(*batch, self.target_dim)
        group = SE2 if self.planar else SE3
        step = group.v_apply(self._omega(target), target[..., self._p_tgt])  # in the body frame
        world = (self._root_rotation(obs) @ step.unsqueeze(-1)).squeeze(-1)
        out[..., self._p_obs] = obs[..., self._p_obs] + world.to(out.dtype)
        return out
