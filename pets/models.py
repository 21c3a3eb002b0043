"""The model variants besides the probabilistic ensembles: deterministic MLPs and the group-feature ablation.

``--model`` values (config key ``head``) and what each one is:

- ``delta``: PETS' probabilistic ensemble (Gaussian NLL) predicting ``next_obs - obs`` (``pets.heads.DeltaHead``).
- ``gem``: the same probabilistic ensemble predicting GEM targets (``gem_head.head.GemHead``); the single
  network of the paper's GEM+PETS experiment.
- ``delta-det`` (:class:`DeterministicDeltaHead` + :class:`DeterministicEnsemble`): the paper's deterministic
  feed-forward baseline. Every member is an MLP predicting ``next_obs - obs`` from DeltaHead's inputs, trained
  by mean squared error (:func:`pets.heads.mse_loss`). ``model.ensemble_size`` members: 1 is the paper's
  single model, 5 its averaged ensemble.
- ``gem2`` (``gem_head.two_stage``): the paper's two-stage GEM (Algorithm 1), deterministic, members as above.
- ``delta-groupfeat`` (:class:`GroupFeatureDeltaHead` + the Gaussian ensemble): an ablation. ``delta``'s
  targets (``next_obs - obs``), probabilistic, NLL, but GEM's input features (cos/sin of hinge angles, rotation
  matrices of quaternions). ``gem`` minus ``delta-groupfeat`` is the gain from composing on the group;
  ``delta-groupfeat`` minus ``delta`` the gain from the input representation. On the planar envs (every group
  ``Rn`` or ``SO2_angle``: InvertedPendulum, Hopper, Walker2d, HalfCheetah) GemHead's targets are
  ``next_obs - obs`` up to the 2 pi wrap of angle differences, which one step never reaches, so there ``gem``
  and ``delta-groupfeat`` are the same model (same inputs, same targets, same predictions for the same seed).

Deterministic models and PETS. The planner, the propagation and the evaluation call
``model(x, members) -> (mean, logvar)`` and sample ``mean + exp(logvar / 2) * eps``. A deterministic model
returns ``logvar = DETERMINISTIC_LOGVAR = -2000`` everywhere: ``exp(-1000)`` underflows to exactly 0 in
float16, bfloat16, float32 and float64, so every sample equals the mean bit for bit (no flag anywhere else).
The value is finite (no inf/NaN arithmetic downstream), but a Gaussian NLL of it is meaningless (inf): the
deterministic heads train by MSE / the Frobenius loss and never call it.

In the paper the ensemble prediction is the average of the members, which is PETS' ``expectation``
propagation (mean over the members' predicted targets, then ``head.next_obs``): the config therefore makes
``planner.propagation=expectation`` the default for ``delta-det`` and ``gem2`` (``pets.config.HEAD_DEFAULTS``;
an explicit ``planner.propagation=`` still wins). ``tsinf`` also works: each particle follows one member,
without noise, so the particles are the members' own trajectories; ``ts1`` mixes members per step.
``pets.evaluate --mode mean`` is the averaged ensemble; ``--mode sample`` follows one member per start.

Training is PETS' ``ModelTrainer`` for every model: per-member bootstrap resamples, holdout early stopping,
elites, and the original PETS per-layer weight decay. With ``model.ensemble_size=5 model.num_elites=5`` the
averaged ensemble uses all five members (the paper's setting); ``model.ensemble_size=1 model.num_elites=1`` is
the single model.
"""

from __future__ import annotations

import torch
from torch import Tensor

from envs.layout import ObsLayout
from gem_head.head import GemHead
from pets.ensemble import MemberEnsemble, _layer_decays, check_member_args, decay_loss, init_member_layers, member_mlp
from pets.heads import DeltaHead, mse_loss

__all__ = ["DETERMINISTIC_LOGVAR", "DeterministicEnsemble", "DeterministicDeltaHead", "GroupFeatureDeltaHead"]

#: Log-variance a deterministic model reports: exp(0.5 * -2000) == 0 exactly in every float dtype.
DETERMINISTIC_LOGVAR = -2000.0


class DeterministicEnsemble(MemberEnsemble):
    """``ensemble_size`` independent MLPs ``x -> mean`` evaluated in one batched pass, no variance.

    Architecture per member: ``num_layers`` hidden layers of ``hidden_size`` SiLU units, then a linear output
    of ``out_dim``; the same batched layers, initialisation, input normaliser and per-layer weight decay as
    :class:`pets.ensemble.GaussianEnsemble`. ``forward`` returns ``(mean, logvar)`` with ``logvar`` filled with
    :data:`DETERMINISTIC_LOGVAR`, so PETS' sampling ``mean + exp(logvar / 2) eps`` returns ``mean`` exactly.
    """

    deterministic = True

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        ensemble_size: int = 5,
        hidden_size: int = 200,
        num_layers: int = 4,
        num_elites: int | None = None,
    ) -> None:
        check_member_args(
            in_dim=in_dim, out_dim=out_dim, ensemble_size=ensemble_size, hidden_size=hidden_size, num_layers=num_layers
        )
        super().__init__(in_dim, out_dim, ensemble_size, num_elites)
        self.hidden_size = hidden_size
        self.num_layers = num_layers
        sizes = [in_dim] + [hidden_size] * num_layers + [out_dim]
        self.weights, self.biases = init_member_layers(sizes, ensemble_size)
        self.decays: list[float] = _layer_decays(len(sizes) - 1)

    def member_parameters(self) -> list[Tensor]:
        """Parameters with a leading member dimension (weights and biases), in a fixed order."""
        return [*self.weights, *self.biases]

    def forward(self, x: Tensor, members: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Mean (M, B, out_dim) of raw inputs ``x`` ((B, in_dim) shared, or (M, B, in_dim)) and the constant
        log-variance :data:`DETERMINISTIC_LOGVAR` of the same shape."""
        idx, _ = self._check_inputs(x, members)
        mean = self.denormalise_target(member_mlp(self.normalise(x), self.weights, self.biases, idx))
        return mean, torch.full_like(mean, DETERMINISTIC_LOGVAR)

    def weight_decay_loss(self) -> Tensor:
        """Per-layer L2 penalty of the original PETS: sum_l decay_l * 0.5 * ||W_l||^2 (all members, no biases)."""
        return decay_loss(self.weights, self.decays)

    def logvar_bound_penalty(self) -> Tensor:
        """Zero: there is no log-variance to bound."""
        return self.weights[0].new_zeros(())

    def extra_repr(self) -> str:
        return (
            f"in_dim={self.in_dim}, out_dim={self.out_dim}, ensemble_size={self.ensemble_size}, "
            f"hidden_size={self.hidden_size}, num_layers={self.num_layers}, num_elites={self.num_elites}, "
            f"deterministic=True"
        )


class DeterministicDeltaHead(DeltaHead):
    """``delta-det``: DeltaHead's inputs, targets (``next_obs - obs``) and decoding; MSE loss, no variance."""

    name = "delta-det"
    deterministic = True

    def loss(
        self, mean: Tensor, logvar: Tensor, target: Tensor, obs: Tensor, next_obs: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        """Per-member mean squared error (E,) of the predicted deltas, each divided by ``scale``; ``logvar`` is
        ignored."""
        return mse_loss(mean, target, scale)


class GroupFeatureDeltaHead(DeltaHead):
    """``delta-groupfeat``: GemHead's inputs (group features), DeltaHead's targets ``next_obs - obs``, Gaussian NLL.

    Inputs are exactly ``GemHead(layout, act_dim).inputs`` (``input_names`` lists them): non-invariant Rn
    coordinates, velocities and other entries, cos/sin of hinge angles, the (cos, sin) pairs, the 9 rotation
    matrix entries of each quaternion, then the action.
    """

    name = "delta-groupfeat"

    def __init__(self, layout: ObsLayout, act_dim: int) -> None:
        super().__init__(layout, act_dim)
        self._features = GemHead(layout, act_dim)
        self.input_dim = self._features.input_dim
        self.input_names: tuple[str, ...] = self._features.input_names

    def inputs(self, obs: Tensor, act: Tensor) -> Tensor:
        """GemHead's network inputs (..., input_dim)."""
        return self._features.inputs(obs, act)
