"""The paper's two-stage GEM (Algorithm 1): a coefficient network, then a velocity network fed its output.

Per member (``gem2`` as a ``--model``), with ``x = GemHead.inputs(obs, act)`` = (G, v, a) as group features:

  alpha_hat = L_alpha(x)                          coefficient network: the group ("static") target slots,
                                                  ``GemHead.group_slots``: the Lie-algebra coefficients of
                                                  every rotation group and the deltas of the Rn coordinates
                                                  (the algebra of R^n is R^n, its exp the identity)
  dv_hat    = L_v(x, (alpha_hat - mu) / sigma)   velocity network: the remaining slots,
                                                  ``GemHead.velocity_slots``: delta velocities and deltas
                                                  of the ``other`` entries

``x`` is normalised by the model's input normaliser. Both networks predict standardised targets (the model's
target normaliser, fitted by ``ModelTrainer`` on the true targets of the training set; identity until then),
so alpha_hat enters the velocity network as ``(alpha_hat - mu) / sigma``, standardised by the mean/std of the
true coefficients. The gradient flows through alpha_hat into the coefficient network:
Algorithm 1 steps both parameter sets along the gradient of the total loss L(phi, psi).

The output is the full target vector in ``GemHead``'s target order (alpha_hat and dv_hat scattered into their
slots), so ``GemHead.next_obs`` decodes it unchanged (exp of each coefficient composed with the current group
element, current + delta elsewhere). Both networks are batched-member MLPs (``dynamics.networks.member_mlp``) with
``model.num_layers`` hidden layers of ``model.hidden_size`` SiLU units each, so ``gem2`` has about twice the
parameters of ``delta-det`` at the same config. The model is deterministic: it reports the constant
log-variance ``dynamics.networks.DETERMINISTIC_LOGVAR`` (sampling noise exactly zero).

Loss (:class:`TwoStageGemHead.loss`) = ``GemHead.frobenius_loss``: per sample
  [ sum over SO(2)/SO(3) groups ||exp(alpha_hat) o G_t - G_{t+1}||_F^2            (L_alpha, eq. LieLoss)
    + sum of squared errors of the Rn slots                                        (L_alpha of the translations)
    + ||dv_hat - dv||^2 over the velocity and other slots ] / target_dim          (L_v, velocity loss)
averaged over the batch: the paper's L = L_alpha + L_v divided by the constant target_dim.

Config: ``gem.compose`` applies (composition in the loss and in decoding); ``gem.loss`` and
``gem.frobenius_weight`` belong to the single-network ``gem`` and are ignored; ``model.*`` sizes both stages.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dynamics.networks import (
    DETERMINISTIC_LOGVAR,
    MemberEnsemble,
    check_member_args,
    decay_loss,
    init_member_layers,
    layer_decays,
    member_mlp,
)
from envs.layout import ObsLayout
from gem_head.head import GemHead

__all__ = ["TwoStageGemHead", "TwoStageGemEnsemble"]


class TwoStageGemHead(GemHead):
    """``gem2``: GemHead's inputs, targets and decoding; deterministic; loss = ``frobenius_loss`` (no NLL).

    ``group_slots`` / ``velocity_slots`` (from GemHead) tell :class:`TwoStageGemEnsemble` which target slots
    each stage predicts.
    """

    name = "gem2"
    deterministic = True

    def __init__(self, layout: ObsLayout, act_dim: int, *, compose: str = "right") -> None:
        super().__init__(layout, act_dim, compose=compose, loss="frobenius")

    def __repr__(self) -> str:
        return (
            f"TwoStageGemHead(obs_dim={self.obs_dim}, act_dim={self.act_dim}, input_dim={self.input_dim}, "
            f"target_dim={self.target_dim}, compose={self.compose!r})"
        )

    def loss(
        self, mean: Tensor, logvar: Tensor, target: Tensor, obs: Tensor, next_obs: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        """Per-member (E,) Frobenius algebraic loss + squared errors of the other slots (``frobenius_loss``, with
        ``scale``); ``logvar`` is ignored."""
        return self.frobenius_loss(mean, target, obs, next_obs, scale)


class TwoStageGemEnsemble(MemberEnsemble):
    """``ensemble_size`` two-stage GEMs (coefficient network -> velocity network) in one batched pass.

    Args:
      in_dim, out_dim: ``head.input_dim``, ``head.target_dim``.
      group_slots, velocity_slots: ``head.group_slots``, ``head.velocity_slots``: disjoint, non-empty, together
        exactly ``range(out_dim)``.
      ensemble_size, hidden_size, num_layers, num_elites: as for the Gaussian ensemble (each stage gets
        ``num_layers`` hidden layers of ``hidden_size``).
    """

    deterministic = True

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        group_slots: tuple[int, ...] | list[int],
        velocity_slots: tuple[int, ...] | list[int],
        ensemble_size: int = 5,
        hidden_size: int = 200,
        num_layers: int = 4,
        num_elites: int | None = None,
        activation: str = "silu",
    ) -> None:
        check_member_args(
            in_dim=in_dim, out_dim=out_dim, ensemble_size=ensemble_size, hidden_size=hidden_size, num_layers=num_layers
        )
        group_slots, velocity_slots = [int(i) for i in group_slots], [int(i) for i in velocity_slots]
        if not group_slots or not velocity_slots or sorted(group_slots + velocity_slots) != list(range(out_dim)):
            raise ValueError(
                f"group_slots and velocity_slots must be non-empty and split range({out_dim}) exactly, "
                f"got {group_slots} and {velocity_slots}"
            )
        super().__init__(in_dim, out_dim, ensemble_size, num_elites, activation)
        self.hidden_size = hidden_size
        self.num_layers = num_layers
        self.group_slots = tuple(group_slots)
        self.velocity_slots = tuple(velocity_slots)
        self.num_coef = len(group_slots)
        hidden = [hidden_size] * num_layers
        self.coef_weights, self.coef_biases = init_member_layers([in_dim, *hidden, self.num_coef], ensemble_size)
        self.vel_weights, self.vel_biases = init_member_layers(
            [in_dim + self.num_coef, *hidden, len(velocity_slots)], ensemble_size
        )
        self.decays: list[float] = layer_decays(num_layers + 1)
        # cat([alpha, dv])[..., order] is the target vector: order[slot] = position of that slot in the cat.
        order = torch.empty(out_dim, dtype=torch.long)
        order[torch.tensor(group_slots + velocity_slots)] = torch.arange(out_dim)
        self.register_buffer("_order", order, persistent=False)

    # ------------------------------------------------------------------ the two stages
    def member_parameters(self) -> list[Tensor]:
        """Parameters with a leading member dimension, in a fixed order (coefficient stage, then velocity stage)."""
        return [*self.coef_weights, *self.coef_biases, *self.vel_weights, *self.vel_biases]

    def coefficient_net(self, h: Tensor, idx: Tensor | None) -> Tensor:
        """Standardised alpha_hat (M, B, num_coef) from normalised inputs ``h`` ((B, in) shared or (M, B, in))."""
        return member_mlp(h, self.coef_weights, self.coef_biases, idx, self.activation)

    def velocity_net(self, h: Tensor, alpha: Tensor, idx: Tensor | None) -> Tensor:
        """Standardised dv_hat (M, B, len(velocity_slots)) from normalised inputs ``h`` and standardised
        coefficients ``alpha`` (M, B, .)."""
        if h.dim() == 2:
            h = h.expand(alpha.shape[0], *h.shape)
        return member_mlp(torch.cat([h, alpha], dim=-1), self.vel_weights, self.vel_biases, idx, self.activation)

    def assemble(self, alpha: Tensor, dv: Tensor) -> Tensor:
        """The target vector (..., out_dim) in GemHead order: alpha in ``group_slots``, dv in ``velocity_slots``."""
        return torch.cat([alpha, dv], dim=-1).index_select(-1, self._order)

    def forward(self, x: Tensor, members: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Predicted targets (M, B, out_dim) of raw inputs ``x`` ((B, in_dim) shared, or (M, B, in_dim)) and the
        constant log-variance ``DETERMINISTIC_LOGVAR`` of the same shape."""
        idx, _ = self._check_inputs(x, members)
        h = self.normalise(x)
        alpha = self.coefficient_net(h, idx)
        mean = self.denormalise_target(self.assemble(alpha, self.velocity_net(h, alpha, idx)))
        return mean, torch.full_like(mean, DETERMINISTIC_LOGVAR)

    # ------------------------------------------------------------------ regularisers
    def weight_decay_loss(self) -> Tensor:
        """The original PETS per-layer L2 penalty, for each stage: sum_l decay_l * 0.5 * ||W_l||^2."""
        return decay_loss(self.coef_weights, self.decays) + decay_loss(self.vel_weights, self.decays)

    def logvar_bound_penalty(self) -> Tensor:
        """Zero: there is no log-variance to bound."""
        return self.coef_weights[0].new_zeros(())

    def extra_repr(self) -> str:
        return (
            f"in_dim={self.in_dim}, out_dim={self.out_dim}, coefficients={self.num_coef}, "
            f"velocities={len(self.velocity_slots)}, ensemble_size={self.ensemble_size}, "
            f"hidden_size={self.hidden_size}, num_layers={self.num_layers}, num_elites={self.num_elites}, "
            f"deterministic=True"
        )
