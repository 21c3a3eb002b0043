"""iCEM (Pinneri et al. 2020): CEM with colored noise, a shrinking population and elite carry-over."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from pets.planning.planners.base import BoxPlanner, Objective, check_real


def colored_noise(
    shape: tuple[int, ...],
    beta: float,
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """Gaussian noise with power spectrum ``S(f) ~ 1 / f^beta`` along the last dimension, unit variance.

    ``shape = (..., T)``; every series of length T is independent. Built in the frequency domain
    (rfft frequencies ``f_k = k / T``, ``k = 0..T//2``): amplitudes ``s_k = max(f_k, 1/T)^(-beta/2)``
    (the DC term gets the amplitude of the lowest frequency), Fourier coefficients
    ``X_k = s_k (a_k + i b_k)`` with ``a, b ~ N(0, 1)``, except that the DC term (and the Nyquist
    term for even T) must be real: ``X_k = sqrt(2) s_k a_k``. Then ``y = irfft(X, T) / sigma`` with
    ``sigma^2 = (2 s_0^2 + 4 sum_{0<k<T/2} s_k^2 + 2 s_{T/2}^2 [T even]) / T^2``, the exact variance of
    every entry of ``irfft(X)``: each ``y_t`` is exactly N(0, 1) and the series is stationary
    (circular). The expected periodogram ``E|rfft(y)_k|^2`` is ``~ f_k^(-beta)`` for ``0 < k < T/2``.
    beta = 0: white noise; 1: pink; 2: red/brown (iCEM's choice for locomotion).
    """
    shape = tuple(int(d) for d in shape)
    if len(shape) < 1 or any(d < 1 for d in shape):
        raise ValueError(f"shape must be non-empty with positive sizes (..., T), got {shape}")
    if isinstance(beta, bool) or not isinstance(beta, numbers.Real) or not math.isfinite(beta) or beta < 0:
        raise ValueError(f"beta (the spectrum exponent) must be a finite number >= 0, got {beta!r}")
    if not dtype.is_floating_point:
        raise ValueError(f"dtype must be a floating dtype, got {dtype}")
    work = torch.float64 if dtype == torch.float64 else torch.float32
    if device is None and generator is not None:
        device = generator.device
    t = shape[-1]
    nf = t // 2 + 1
    k = torch.arange(nf, device=device, dtype=work)
    s = torch.clamp(k / t, min=1.0 / t) ** (-0.5 * float(beta))
    real_only = torch.zeros(nf, dtype=torch.bool, device=device)
    real_only[0] = True
    if t % 2 == 0:
        real_only[-1] = True
    re_scale = torch.where(real_only, math.sqrt(2.0) * s, s)
    im_scale = torch.where(real_only, torch.zeros_like(s), s)
    multiplicity = torch.where(real_only, 1.0, 2.0).to(work)  # interior terms appear twice (k and T - k)
    sigma = torch.sqrt(((re_scale**2 + im_scale**2) * multiplicity).sum()) / t
    z = torch.randn(shape[:-1] + (nf, 2), generator=generator, device=device, dtype=work)
    spec = torch.complex(z[..., 0] * re_scale, z[..., 1] * im_scale)
    y = torch.fft.irfft(spec, n=t, dim=-1) / sigma
    return y.to(dtype)


@dataclass
class ICEMConfig:
    """``planner.icem.*``: the iCEM planner's own settings in the config (:class:`ICEMPlanner`)."""

    noise_beta: float = 2.0  # colored-noise exponent: 0 white, 2 red (the iCEM paper's locomotion choice)
    population_decay: float = 1.25  # population_i = max(population * decay^-i, 2 * elites)
    keep_elites: float = 0.3  # fraction of the elites carried into the next iteration / MPC step

    def checked(self) -> ICEMConfig:
        """The arguments validated (a ValueError naming the first out of range)."""
        return replace(
            self,
            noise_beta=check_real("noise_beta", self.noise_beta, 0.0, math.inf),
            population_decay=check_real("population_decay", self.population_decay, 1.0, math.inf),
            keep_elites=check_real("keep_elites", self.keep_elites, 0.0, 1.0),
        )


@dataclass
class ICEMOptions(ICEMConfig):
    """All of iCEM's own arguments: its config section and two that the config leaves at these defaults."""

    return_mean_elites: bool = False
    keep_between_steps: bool = True


def _shift_rows(x: Tensor, k: int, fill: Tensor) -> Tensor:
    """``x`` (..., H, A) moved ``k`` steps earlier along H, the last ``k`` steps set to ``fill`` (A,)."""
    if k == 0:
        return x
    tail = fill.expand(*x.shape[:-2], k, x.shape[-1])
    return torch.cat([x[..., k:, :], tail], dim=-2)


class ICEMPlanner(BoxPlanner):
    """iCEM (Pinneri et al. 2020) over (horizon, act_dim) action sequences within box bounds.

    Iteration ``i`` (0-based) of a ``plan`` call:

    1. samples ``N_i = max(floor(population * population_decay^-i), 2 * elites)`` sequences
       ``clip(mu + std * c)`` with ``c`` colored noise of exponent ``noise_beta`` along the horizon
       (:func:`colored_noise`, independent per action dimension);
    2. adds ``n_keep = ceil(keep_elites * elites)`` carried sequences: the best ``n_keep`` elites of
       iteration ``i - 1``; at ``i = 0`` the best ``n_keep`` elites of the previous ``plan`` call,
       shifted like the warm start (only when ``init_mean`` is recognised as the previous result
       shifted by ``k`` steps by :func:`shift_plan`, as :class:`pets.agent.MPCAgent` passes it);
    3. at the last iteration also adds the mean ``mu`` itself;
    4. scores everything with the objective, takes the ``elites`` best, and updates
       ``mu = alpha * mu + (1 - alpha) * mean(elites)``, ``std = alpha * std + (1 - alpha) * std(elites)``
       (population std).

    Initial mean: the warm start (clipped) or the middle of the bounds; initial std ``(ub - lb) / 4``
    (as CEM's initial variance ``(ub - lb)^2 / 16``). The result is the best sample of the last
    iteration's population (the paper's choice; it includes the carried elites and the mean), or
    the final mean with ``return_mean_elites=True``. The objective sees populations of varying size
    ``N_i + n_keep (+ 1)``.

    elites: a count (int, 1..population) or a ratio of ``population`` (float in (0, 1]).
    noise_beta: spectrum exponent (>= 0; 0 = white noise, the paper uses 2-2.5 for locomotion).
    population_decay: gamma >= 1 (1 = constant population; the paper uses 1.25).
    keep_elites: fraction xi in [0, 1] of the elites carried over (the paper uses 0.3).
    keep_between_steps: also carry the previous call's elites into the first iteration.
    """

    name = "icem"
    Options = ICEMOptions
    section = ICEMConfig
    uses_elites = True
    gains_note = "iCEM's coloured noise and carried elites act along a time axis that gains do not have"

    def setup(self) -> None:
        """The carried elites per iteration, the population of each iteration, nothing carried yet."""
        self.num_keep = min(self.num_elites, math.ceil(round(self.keep_elites * self.num_elites, 4)))
        #: fresh samples per iteration (N_i)
        self.populations = [
            max(int(self.population * self.population_decay ** (-i)), 2 * self.num_elites)
            for i in range(self.iterations)
        ]
        self._last_plan: Tensor | None = None
        self._last_elites: Tensor | None = None
        self._elites: Tensor | None = None

    def reset(self) -> None:
        """Forget the elites kept from the previous call."""
        self._last_plan = None
        self._last_elites = None

    def _carried_from_last_call(self, init_mean: Tensor | None) -> Tensor | None:
        """The previous call's best elites shifted like ``init_mean``, or None if it is not a shifted previous plan."""
        if not self.keep_between_steps or self.num_keep == 0 or init_mean is None or self._last_plan is None:
            return None
        h = self.horizon
        init = torch.as_tensor(init_mean, device=self.device, dtype=self.dtype)
        if init.shape != self._last_plan.shape:
            return None
        mid = 0.5 * (self.low + self.high)
        shifts = torch.arange(h + 1, device=self.device)  # candidate shift k = 0..H
        src = torch.arange(h, device=self.device)[None, :] + shifts[:, None]  # (H + 1, H)
        cand = torch.where((src < h)[..., None], self._last_plan[src.clamp(max=h - 1)], mid)  # (H + 1, H, A)
        match = (cand == init).flatten(1).all(dim=1)
        hits = torch.nonzero(match).flatten().tolist()  # one host synchronisation per plan call
        if not hits:
            return None
        return _shift_rows(self._last_elites[: self.num_keep], hits[0], mid)

    def search(
        self, objective: Objective, mu: Tensor, init_mean: Tensor | None, generator: torch.Generator | None
    ) -> Tensor:
        """iCEM's iterations (the class docstring): the best sample of the last iteration, or the final mean."""
        h, a = self.horizon, self.act_dim
        carry = self._carried_from_last_call(init_mean)
        std = (0.25 * (self.high - self.low)).expand(h, a).clone()
        elite = best = None
        for i in range(self.iterations):
            n = self.populations[i]
            noise = colored_noise(
                (n, a, h), self.noise_beta, generator=generator, device=self.device, dtype=self.dtype
            ).transpose(1, 2)  # (n, H, A), colored along H
            parts = [self.clip(mu + std * noise)]
            if carry is not None:
                parts.append(carry)
            if i == self.iterations - 1:
                parts.append(mu.unsqueeze(0))
            samples = torch.cat(parts) if len(parts) > 1 else parts[0]
            values = torch.nan_to_num(objective(samples), nan=-math.inf)
            _, idx = torch.topk(values, self.num_elites)  # sorted, best first
            elite = samples.index_select(0, idx)
            best = elite[0]
            mu = self.alpha * mu + (1.0 - self.alpha) * elite.mean(dim=0)
            std = self.alpha * std + (1.0 - self.alpha) * elite.std(dim=0, unbiased=False)
            carry = elite[: self.num_keep] if self.num_keep > 0 else None
        self._elites = elite
        return mu if self.return_mean_elites else best

    def planned(self, plan: Tensor) -> None:
        """Keep the plan and its call's elites for the next call (only after a successful call)."""
        self._last_plan, self._last_elites = plan, self._elites
