"""MPPI: Gaussian perturbations of the mean, smoothed in time, weighted by a softmax of the returns."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from pets.planning.planners.base import BoxPlanner, Objective, check_positive_ints, check_real


def smoothing_matrix(
    horizon: int, smoothing: float, *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
) -> Tensor:
    """(H, H) lower-triangular filter ``L`` so that ``u = L @ n`` smooths i.i.d. N(0, 1) noise ``n`` in time.

    ``u_0 = n_0``, ``u_t = smoothing * n_t + (1 - smoothing) * u_{t-1}`` (a first-order low-pass), then
    each row is divided by its norm so that every ``u_t`` is again exactly N(0, 1): the smoothing sets
    the correlation between steps (``corr(u_t, u_{t+1}) -> 1 - smoothing`` for large t), not the spread.
    ``smoothing = 1`` gives the identity (independent steps).
    """
    check_positive_ints(horizon=horizon)
    beta = check_real("smoothing", smoothing, 0.0, 1.0, low_open=True)
    t = torch.arange(horizon, dtype=torch.float64)
    lag = t[:, None] - t[None, :]
    decay = torch.where(lag >= 0, (1.0 - beta) ** lag.clamp(min=0), torch.zeros(()))
    first = torch.where(t[None, :] == 0, torch.ones(()), torch.full((), beta))  # n_0 enters with weight 1
    filt = torch.tril(decay * first)
    filt = filt / filt.norm(dim=1, keepdim=True)
    return filt.to(device=device, dtype=dtype)


@dataclass
class MPPIConfig:
    """``planner.mppi.*``: the MPPI planner's own arguments (:class:`MPPIPlanner`)."""

    sigma: float = 0.5  # perturbation std in units of the action half-range (ub - lb) / 2
    temperature: float = 0.3  # softmax temperature on returns normalised by (max - median)
    smoothing: float = 1.0  # low-pass coefficient in (0, 1] along the horizon; 1 = independent steps

    def checked(self) -> MPPIConfig:
        """The arguments validated (a ValueError naming the first out of range)."""
        return replace(
            self,
            sigma=check_real("sigma", self.sigma, 0.0, math.inf, low_open=True),
            temperature=check_real("temperature", self.temperature, 0.0, math.inf, low_open=True),
            smoothing=check_real("smoothing", self.smoothing, 0.0, 1.0, low_open=True),
        )


class MPPIPlanner(BoxPlanner):
    """MPPI over (horizon, act_dim) action sequences within box bounds.

    Iteration (``iterations`` refinement passes from the warm start or the middle of the bounds):

    1. ``population`` perturbations ``eps = sigma * (ub - lb) / 2 * (L @ n)``, ``n ~ N(0, I)`` i.i.d.
       over (horizon, act_dim), ``L`` the :func:`smoothing_matrix` (identity for ``smoothing = 1``);
       samples ``clip(mu + eps)``. ``sigma`` is in units of the half-range of the actions: 1.0 is
       lifelong_rl's ``noise_std = 1`` for actions in [-1, 1] (heavily clipped); every step's
       perturbation has exactly that std whatever the smoothing.
    2. Returns ``R`` (higher is better) are normalised per iteration as
       ``z = (R - max R) / (max R - median R)`` (``z <= 0``, the best is 0 and the median -1; 1e-12
       guards a flat spread); NaN and infinite returns count as the worst finite return. Weights
       ``w = softmax(z / temperature)``. (lifelong_rl normalises by ``max - min`` instead; the median
       makes the scale robust to a few diverged rollouts, which the evaluator scores -1e6.)
    3. ``mu = alpha * mu + (1 - alpha) * sum_i w_i samples_i`` (lifelong_rl's polyak; PETS's alpha 0.1).

    The result is the final ``mu`` (in bounds: a convex combination of clipped samples). temperature
    -> 0 gives the best sample (random shooting), temperature -> inf the plain sample mean. The
    planner keeps no state between calls.
    """

    name = "mppi"
    Options = MPPIConfig
    section = MPPIConfig

    @classmethod
    def gain_options(cls, gain_bound: float, gain_std: float) -> dict[str, float] | None:
        """``sigma`` in half-ranges of the gains' box."""
        return {"sigma": gain_std / gain_bound}

    def setup(self) -> None:
        """The smoothing filter (none for independent steps)."""
        self._filter = (
            None
            if self.smoothing == 1.0
            else smoothing_matrix(self.horizon, self.smoothing, device=self.device, dtype=self.dtype)
        )

    def weights(self, values: Tensor) -> Tensor:
        """Softmax weights (N,) of returns (N,) after the normalisation above (see the class docstring)."""
        values = values.to(self.dtype)
        finite = torch.isfinite(values)
        any_finite = finite.any()
        worst = torch.where(finite, values, math.inf).amin()
        v = torch.where(finite, values, torch.where(any_finite, worst, torch.zeros_like(worst)))
        top = v.amax()
        spread = (top - v.median()).clamp(min=1e-12)
        return torch.softmax((v - top) / (spread * self.temperature), dim=0)

    def search(
        self, objective: Objective, mu: Tensor, init_mean: Tensor | None, generator: torch.Generator | None
    ) -> Tensor:
        """MPPI's iterations (the class docstring): the final mean."""
        h, a = self.horizon, self.act_dim
        scale = self.sigma * 0.5 * (self.high - self.low)
        for _ in range(self.iterations):
            n = torch.randn((self.population, h, a), generator=generator, device=self.device, dtype=self.dtype)
            if self._filter is not None:
                n = torch.matmul(self._filter, n)  # (H, H) @ (N, H, A): smoothed along the horizon
            samples = self.clip(mu + scale * n)
            w = self.weights(objective(samples))
            mu = self.alpha * mu + (1.0 - self.alpha) * torch.einsum("n,nha->ha", w, samples)
        return mu
