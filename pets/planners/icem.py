"""iCEM (Pinneri et al. 2020): CEM with colored noise, a shrinking population and elite carry-over."""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable

import torch
from torch import Tensor

from pets.planners.base import (
    BoxPlanner,
    check_generator,
    check_planned,
    check_real,
    check_values,
    elite_count,
    initial_mean,
    no_finite,
)


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

    uses_elites = True

    def __init__(
        self,
        action_low: object,
        action_high: object,
        *,
        horizon: int,
        population: int,
        elites: int | float = 0.1,
        iterations: int = 5,
        alpha: float = 0.1,
        noise_beta: float = 2.0,
        population_decay: float = 1.25,
        keep_elites: float = 0.3,
        return_mean_elites: bool = False,
        keep_between_steps: bool = True,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        common = dict(horizon=horizon, population=population, iterations=iterations, alpha=alpha)
        super().__init__(action_low, action_high, **common, device=device, dtype=dtype)
        self.num_elites = elite_count(elites, population)
        self.noise_beta, self.population_decay, self.keep_elites = self.check_args(
            noise_beta=noise_beta, population_decay=population_decay, keep_elites=keep_elites
        )
        self.return_mean_elites = bool(return_mean_elites)
        self.keep_between_steps = bool(keep_between_steps)
        self.num_keep = min(self.num_elites, math.ceil(round(self.keep_elites * self.num_elites, 4)))
        #: fresh samples per iteration (N_i)
        self.populations = [
            max(int(population * self.population_decay ** (-i)), 2 * self.num_elites) for i in range(iterations)
        ]
        self._last_plan: Tensor | None = None
        self._last_elites: Tensor | None = None

    @staticmethod
    def check_args(*, noise_beta: float, population_decay: float, keep_elites: float) -> tuple[float, float, float]:
        """The iCEM-only arguments as floats, or a ValueError naming the first out of range (also the config's
        check of ``planner.icem.*``)."""
        return (
            check_real("noise_beta", noise_beta, 0.0, math.inf),
            check_real("population_decay", population_decay, 1.0, math.inf),
            check_real("keep_elites", keep_elites, 0.0, 1.0),
        )

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

    def plan(
        self,
        objective: Callable[[Tensor], Tensor],
        init_mean: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Optimise ``objective`` ((N, H, act_dim) -> (N,), higher is better); returns (H, act_dim) in bounds.

        init_mean: warm start (H, act_dim), clipped to the bounds; default the middle of the bounds
          (and no elites carried from the previous call).
        generator: source of all the randomness (on the planner's device).
        """
        h, a = self.horizon, self.act_dim
        lb, ub = self.low, self.high
        check_generator(generator, self.device)
        carry = self._carried_from_last_call(init_mean)
        mu = initial_mean(init_mean, lb, ub, h, a)
        std = (0.25 * (ub - lb)).expand(h, a).clone()
        elite = best = None
        failed = torch.zeros((), dtype=torch.bool, device=self.device)
        for i in range(self.iterations):
            n = self.populations[i]
            noise = colored_noise(
                (n, a, h), self.noise_beta, generator=generator, device=self.device, dtype=self.dtype
            ).transpose(1, 2)  # (n, H, A), colored along H
            parts = [torch.minimum(torch.maximum(mu + std * noise, lb), ub)]
            if carry is not None:
                parts.append(carry)
            if i == self.iterations - 1:
                parts.append(mu.unsqueeze(0))
            samples = torch.cat(parts) if len(parts) > 1 else parts[0]
            values = check_values(objective(samples), samples.shape[0], self.dtype)
            failed = failed | no_finite(values)
            values = torch.nan_to_num(values, nan=-math.inf)
            _, idx = torch.topk(values, self.num_elites)  # sorted, best first
            elite = samples.index_select(0, idx)
            best = elite[0]
            mu = self.alpha * mu + (1.0 - self.alpha) * elite.mean(dim=0)
            std = self.alpha * std + (1.0 - self.alpha) * elite.std(dim=0, unbiased=False)
            carry = elite[: self.num_keep] if self.num_keep > 0 else None
        check_planned(failed)  # before keeping this call's elites for the next one
        out = mu if self.return_mean_elites else best
        out = torch.minimum(torch.maximum(out, lb), ub)
        self._last_plan, self._last_elites = out, elite
        return out
