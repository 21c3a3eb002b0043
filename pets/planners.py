"""Planners over action sequences: CEM (as PETS uses it), iCEM and MPPI, and the MPC warm start.

All three share the API ``plan(objective, init_mean=None, generator=None) -> (H, act_dim)``: the
objective maps (N, H, act_dim) candidates to (N,) values (higher is better, NaN counts as the
worst), every sample and the result lie within the action bounds, and all randomness comes from
``generator`` (same generator state -> same plan).

CEM (``CEMPlanner``, below).

CEM keeps a diagonal Gaussian over the (H, act_dim) action sequence. Each iteration it

1. constrains the variance so that 2 standard deviations stay inside the bounds:
   ``var_c = min(var, (min(mu - lb, ub - mu) / 2)^2)``;
2. samples ``population`` sequences ``mu + sqrt(var_c) * z`` with ``z`` a standard normal
   truncated to [-2, 2] (inverse-CDF sampling, see :func:`truncated_normal`), clipped to the
   bounds against rounding;
3. scores them with the objective (higher is better; NaN counts as -inf) and takes the
   ``elites`` best;
4. smooths: ``mu = alpha * mu + (1 - alpha) * mean(elites)``, ``var = alpha * var + (1 - alpha) * var(elites)``
   (population variance, as ``np.var``).

The initial mean is the middle of the bounds (or the warm start), the initial variance
``(ub - lb)^2 / 16``. The result is the final CEM mean ``mu`` (the smoothed elite mean of the
last iteration, what PETS returns), or with ``return_mean_elites=False`` the best sample seen.
The planner keeps no state between calls other than its configuration.

iCEM (``ICEMPlanner``, Pinneri et al. 2020, "Sample-efficient cross-entropy method for real-time
planning"): CEM with colored-noise samples (:func:`colored_noise`), a population that shrinks by
``population_decay`` per iteration (never below twice the elites), a fraction of the previous
iteration's elites carried into the next population (and, between MPC steps, of the previous
plan's elites, shifted), the mean added to the last population, and the best sample executed.

MPPI (``MPPIPlanner``, model-predictive path integral control as in the lifelong_rl code the GEM
paper planned with): Gaussian perturbations of the current mean, optionally smoothed in time,
weighted by a softmax of the normalised returns.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from typing import Protocol

import torch
from torch import Tensor


def truncated_normal(
    shape: tuple[int, ...], mean: Tensor, std: Tensor, *, bound: float = 2.0, generator: torch.Generator | None = None
) -> Tensor:
    """Samples of N(mean, std^2) truncated to ``mean +- bound * std``, shape ``shape + mean.shape``.

    Inverse-CDF method: ``u ~ U(Phi(-bound), Phi(bound))``, ``z = sqrt(2) erfinv(2 u - 1)``
    (so ``z = Phi^-1(u)`` is a standard normal truncated to [-bound, bound]), clamped to
    [-bound, bound] against rounding; result ``mean + std * z``. ``mean`` and ``std`` broadcast.
    Rejection-free, so the cost is fixed and all randomness comes from ``generator``.
    """
    if not bound > 0:
        raise ValueError(f"bound must be > 0 standard deviations, got {bound}")
    mean, std = torch.broadcast_tensors(mean, std)
    lo = 0.5 * math.erfc(bound / math.sqrt(2.0))
    u = torch.rand(tuple(shape) + tuple(mean.shape), generator=generator, device=mean.device, dtype=mean.dtype)
    u = lo + (1.0 - 2.0 * lo) * u
    z = math.sqrt(2.0) * torch.erfinv(2.0 * u - 1.0)
    z = z.clamp(-bound, bound)
    return mean + std * z


def _as_bounds(
    low: object, high: object, device: torch.device | str | None, dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """Validated (act_dim,) bound tensors on ``device`` (checked on the host, before the move)."""
    lb = torch.as_tensor(low).detach().to("cpu", torch.float64).reshape(-1)
    ub = torch.as_tensor(high).detach().to("cpu", torch.float64).reshape(-1)
    if lb.shape != ub.shape or lb.numel() == 0:
        raise ValueError(
            f"action_low and action_high must be non-empty and of the same length, "
            f"got {tuple(lb.shape)} and {tuple(ub.shape)}"
        )
    if not (torch.isfinite(lb).all() and torch.isfinite(ub).all()):
        raise ValueError("action bounds must be finite")
    if not (lb < ub).all():
        raise ValueError(f"every action_low must be < action_high, got low={lb.tolist()} high={ub.tolist()}")
    return lb.to(device=device, dtype=dtype), ub.to(device=device, dtype=dtype)


def shift_plan(plan: Tensor, action_low: object, action_high: object) -> Tensor:
    """Warm start for the next MPC step: drop the first action, append the middle of the bounds.

    plan (H, act_dim) -> (H, act_dim): ``[plan[1], ..., plan[H-1], (low + high) / 2]``.
    """
    if plan.dim() != 2:
        raise ValueError(f"plan must have shape (H, act_dim), got {tuple(plan.shape)}")
    # No value checks here (they would synchronise with the device every MPC step): the planner validates bounds.
    lb = torch.as_tensor(action_low, device=plan.device, dtype=plan.dtype).reshape(-1)
    ub = torch.as_tensor(action_high, device=plan.device, dtype=plan.dtype).reshape(-1)
    if lb.numel() != plan.shape[1] or ub.numel() != plan.shape[1]:
        raise ValueError(f"plan has act_dim {plan.shape[1]} but the bounds have {lb.numel()} and {ub.numel()} entries")
    mid = 0.5 * (lb + ub)
    return torch.cat([plan[1:], mid.unsqueeze(0)], dim=0)


class Planner(Protocol):
    """What the MPC agent needs of a planner: one optimisation of a return objective."""

    horizon: int

    def plan(
        self,
        objective: Callable[[Tensor], Tensor],
        init_mean: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> Tensor: ...

    def reset(self) -> None:
        """Forget what the planner carries from one call to the next (before an unrelated plan)."""
        ...


class CEMPlanner:
    """Cross-entropy method over (horizon, act_dim) action sequences within box bounds.

    action_low, action_high: (act_dim,) finite bounds, low < high.
    horizon, population, iterations: positive ints.
    elites: a count (int, 1..population) or a ratio (float in (0, 1]; count = ceil(ratio * population)).
    alpha: smoothing in [0, 1]: ``mu = alpha * mu + (1 - alpha) * elite_mean`` (same for var).
    epsilon: PETS's early stop: stop iterating once every variance is below it (0 disables it;
      when enabled it costs one host synchronisation per iteration).
    return_mean_elites: return the final CEM mean (PETS), else the best sample seen.
    device, dtype: where the samples live (the objective gets tensors there).
    """

    #: Whether the constructor takes ``elites`` (the config's ``planner.elites``).
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
        epsilon: float = 0.0,
        return_mean_elites: bool = True,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        for name, val in (("horizon", horizon), ("population", population), ("iterations", iterations)):
            if isinstance(val, bool) or not isinstance(val, int) or val < 1:
                raise ValueError(f"{name} must be a positive int, got {val!r}")
        if isinstance(elites, bool) or not isinstance(elites, numbers.Real):
            raise ValueError(f"elites must be an int count or a float ratio, got {elites!r}")
        if isinstance(elites, numbers.Integral):
            if not 1 <= elites <= population:
                raise ValueError(f"elites as a count must be in [1, population={population}], got {elites}")
            num_elites = int(elites)
        else:
            if not 0.0 < elites <= 1.0:
                raise ValueError(f"elites as a ratio must be in (0, 1], got {elites}")
            num_elites = min(population, max(1, math.ceil(round(float(elites) * population, 4))))
        if not 0.0 <= alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {alpha}")
        if not epsilon >= 0.0:
            raise ValueError(f"epsilon must be >= 0, got {epsilon}")
        self.low, self.high = _as_bounds(action_low, action_high, device, dtype)
        self.act_dim = self.low.numel()
        self.horizon = horizon
        self.population = population
        self.num_elites = num_elites
        self.iterations = iterations
        self.alpha = float(alpha)
        self.epsilon = float(epsilon)
        self.return_mean_elites = return_mean_elites
        self.device = self.low.device
        self.dtype = dtype

    def reset(self) -> None:
        """Nothing to forget: every call starts from ``init_mean`` (or the box centre)."""

    def plan(
        self,
        objective: Callable[[Tensor], Tensor],
        init_mean: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Optimise ``objective`` ((N, H, act_dim) -> (N,), higher is better); returns (H, act_dim) in bounds.

        init_mean: warm start (H, act_dim), clipped to the bounds; default the middle of the bounds.
        generator: source of all the randomness (on the planner's device).
        """
        h, a = self.horizon, self.act_dim
        lb, ub = self.low, self.high
        _check_generator(generator, self.device)
        mu = _initial_mean(init_mean, lb, ub, h, a)
        var = ((ub - lb) ** 2 / 16.0).expand(h, a).clone()
        best_value = torch.full((), -math.inf, device=self.device, dtype=self.dtype)
        best = mu.clone()

        for _ in range(self.iterations):
            dist = torch.minimum(mu - lb, ub - mu)
            var_c = torch.minimum(var, (0.5 * dist) ** 2)
            samples = truncated_normal((self.population,), mu, var_c.sqrt(), generator=generator)
            samples = torch.minimum(torch.maximum(samples, lb), ub)
            values = objective(samples)
            if values.shape != (self.population,):
                raise ValueError(f"objective must return shape ({self.population},), got {tuple(values.shape)}")
            values = torch.nan_to_num(values.to(self.dtype), nan=-math.inf)
            top, idx = torch.topk(values, self.num_elites)
            elite = samples.index_select(0, idx)
            if not self.return_mean_elites:
                better = top[0] > best_value
                best = torch.where(better, elite[0], best)
                best_value = torch.where(better, top[0], best_value)
            mu = self.alpha * mu + (1.0 - self.alpha) * elite.mean(dim=0)
            var = self.alpha * var + (1.0 - self.alpha) * elite.var(dim=0, unbiased=False)
            if self.epsilon > 0.0 and bool(var.max() < self.epsilon):
                break

        out = mu if self.return_mean_elites else best
        return torch.minimum(torch.maximum(out, lb), ub)


# ---------------------------------------------------------------------------------------------- helpers
def _check_positive_ints(**values: object) -> None:
    for name, val in values.items():
        if isinstance(val, bool) or not isinstance(val, int) or val < 1:
            raise ValueError(f"{name} must be a positive int, got {val!r}")


def _elite_count(elites: object, population: int) -> int:
    """Elites as a count (int in [1, population]) or a ratio of the population (float in (0, 1], ceil)."""
    if isinstance(elites, bool) or not isinstance(elites, numbers.Real):
        raise ValueError(f"elites must be an int count or a float ratio, got {elites!r}")
    if isinstance(elites, numbers.Integral):
        if not 1 <= elites <= population:
            raise ValueError(f"elites as a count must be in [1, population={population}], got {elites}")
        return int(elites)
    if not 0.0 < elites <= 1.0:
        raise ValueError(f"elites as a ratio must be in (0, 1], got {elites}")
    return min(population, max(1, math.ceil(round(float(elites) * population, 4))))


def _check_real(
    name: str, value: object, low: float, high: float, *, low_open: bool = False, high_open: bool = False
) -> float:
    """``value`` as a float in the interval [low, high] (open ends as asked), else a ValueError."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    v = float(value)
    if (v < low or (low_open and v == low)) or (v > high or (high_open and v == high)):
        lo, hi = ("(" if low_open else "[") + f"{low}", f"{high}" + (")" if high_open else "]")
        raise ValueError(f"{name} must be in {lo}, {hi}, got {value}")
    return v


def _check_generator(generator: torch.Generator | None, device: torch.device) -> None:
    if generator is not None and generator.device.type != device.type:
        raise ValueError(f"generator is on {generator.device}, the planner on {device}")


def _initial_mean(init_mean: Tensor | None, lb: Tensor, ub: Tensor, h: int, a: int) -> Tensor:
    """The warm start clipped to the bounds, or the middle of the bounds; shape (h, a)."""
    if init_mean is None:
        return (0.5 * (lb + ub)).expand(h, a).clone()
    mu = torch.as_tensor(init_mean, device=lb.device, dtype=lb.dtype)
    if mu.shape != (h, a):
        raise ValueError(f"init_mean must have shape ({h}, {a}), got {tuple(mu.shape)}")
    return torch.minimum(torch.maximum(mu, lb), ub)


def _check_values(values: Tensor, n: int, dtype: torch.dtype) -> Tensor:
    if not isinstance(values, Tensor) or values.shape != (n,):
        shape = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
        raise ValueError(f"objective must return shape ({n},), got {shape}")
    return values.to(dtype)


# ---------------------------------------------------------------------------------------------- iCEM
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


class ICEMPlanner:
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

    #: Whether the constructor takes ``elites`` (the config's ``planner.elites``).
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
        _check_positive_ints(horizon=horizon, population=population, iterations=iterations)
        self.num_elites = _elite_count(elites, population)
        self.alpha = _check_real("alpha", alpha, 0.0, 1.0)
        self.noise_beta = _check_real("noise_beta", noise_beta, 0.0, math.inf)
        self.population_decay = _check_real("population_decay", population_decay, 1.0, math.inf)
        self.keep_elites = _check_real("keep_elites", keep_elites, 0.0, 1.0)
        self.low, self.high = _as_bounds(action_low, action_high, device, dtype)
        self.act_dim = self.low.numel()
        self.horizon = horizon
        self.population = population
        self.iterations = iterations
        self.return_mean_elites = bool(return_mean_elites)
        self.keep_between_steps = bool(keep_between_steps)
        self.device = self.low.device
        self.dtype = dtype
        self.num_keep = min(self.num_elites, math.ceil(round(self.keep_elites * self.num_elites, 4)))
        #: fresh samples per iteration (N_i)
        self.populations = [
            max(int(population * self.population_decay ** (-i)), 2 * self.num_elites) for i in range(iterations)
        ]
        self._last_plan: Tensor | None = None
        self._last_elites: Tensor | None = None

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
        _check_generator(generator, self.device)
        carry = self._carried_from_last_call(init_mean)
        mu = _initial_mean(init_mean, lb, ub, h, a)
        std = (0.25 * (ub - lb)).expand(h, a).clone()
        elite = best = None
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
            values = _check_values(objective(samples), samples.shape[0], self.dtype)
            values = torch.nan_to_num(values, nan=-math.inf)
            _, idx = torch.topk(values, self.num_elites)  # sorted, best first
            elite = samples.index_select(0, idx)
            best = elite[0]
            mu = self.alpha * mu + (1.0 - self.alpha) * elite.mean(dim=0)
            std = self.alpha * std + (1.0 - self.alpha) * elite.std(dim=0, unbiased=False)
            carry = elite[: self.num_keep] if self.num_keep > 0 else None
        out = mu if self.return_mean_elites else best
        out = torch.minimum(torch.maximum(out, lb), ub)
        self._last_plan, self._last_elites = out, elite
        return out


# ---------------------------------------------------------------------------------------------- MPPI
def smoothing_matrix(
    horizon: int, smoothing: float, *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
) -> Tensor:
    """(H, H) lower-triangular filter ``L`` so that ``u = L @ n`` smooths i.i.d. N(0, 1) noise ``n`` in time.

    ``u_0 = n_0``, ``u_t = smoothing * n_t + (1 - smoothing) * u_{t-1}`` (a first-order low-pass), then
    each row is divided by its norm so that every ``u_t`` is again exactly N(0, 1): the smoothing sets
    the correlation between steps (``corr(u_t, u_{t+1}) -> 1 - smoothing`` for large t), not the spread.
    ``smoothing = 1`` gives the identity (independent steps).
    """
    _check_positive_ints(horizon=horizon)
    beta = _check_real("smoothing", smoothing, 0.0, 1.0, low_open=True)
    t = torch.arange(horizon, dtype=torch.float64)
    lag = t[:, None] - t[None, :]
    decay = torch.where(lag >= 0, (1.0 - beta) ** lag.clamp(min=0), torch.zeros(()))
    first = torch.where(t[None, :] == 0, torch.ones(()), torch.full((), beta))  # n_0 enters with weight 1
    filt = torch.tril(decay * first)
    filt = filt / filt.norm(dim=1, keepdim=True)
    return filt.to(device=device, dtype=dtype)


class MPPIPlanner:
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

    #: Whether the constructor takes ``elites`` (the config's ``planner.elites``).
    uses_elites = False

    def __init__(
        self,
        action_low: object,
        action_high: object,
        *,
        horizon: int,
        population: int,
        iterations: int = 5,
        alpha: float = 0.1,
        sigma: float = 0.5,
        temperature: float = 0.3,
        smoothing: float = 1.0,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        _check_positive_ints(horizon=horizon, population=population, iterations=iterations)
        self.alpha = _check_real("alpha", alpha, 0.0, 1.0)
        self.sigma = _check_real("sigma", sigma, 0.0, math.inf, low_open=True)
        self.temperature = _check_real("temperature", temperature, 0.0, math.inf, low_open=True)
        self.smoothing = _check_real("smoothing", smoothing, 0.0, 1.0, low_open=True)
        self.low, self.high = _as_bounds(action_low, action_high, device, dtype)
        self.act_dim = self.low.numel()
        self.horizon = horizon
        self.population = population
        self.iterations = iterations
        self.device = self.low.device
        self.dtype = dtype
        self._filter = (
            None
            if self.smoothing == 1.0
            else smoothing_matrix(horizon, self.smoothing, device=self.device, dtype=dtype)
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

    def reset(self) -> None:
        """Nothing to forget: every call starts from ``init_mean`` (or the box centre)."""

    def plan(
        self,
        objective: Callable[[Tensor], Tensor],
        init_mean: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Optimise ``objective`` ((N, H, act_dim) -> (N,), higher is better); returns (H, act_dim) in bounds.

        init_mean: warm start (H, act_dim), clipped to the bounds; default the middle of the bounds.
        generator: source of all the randomness (on the planner's device).
        """
        h, a = self.horizon, self.act_dim
        lb, ub = self.low, self.high
        _check_generator(generator, self.device)
        mu = _initial_mean(init_mean, lb, ub, h, a)
        scale = self.sigma * 0.5 * (ub - lb)
        for _ in range(self.iterations):
            n = torch.randn((self.population, h, a), generator=generator, device=self.device, dtype=self.dtype)
            if self._filter is not None:
                n = torch.matmul(self._filter, n)  # (H, H) @ (N, H, A): smoothed along the horizon
            samples = torch.minimum(torch.maximum(mu + scale * n, lb), ub)
            values = _check_values(objective(samples), self.population, self.dtype)
            w = self.weights(values)
            mu = self.alpha * mu + (1.0 - self.alpha) * torch.einsum("n,nha->ha", w, samples)
        return torch.minimum(torch.maximum(mu, lb), ub)


#: The table of planners (``planner.name``): each name's class. ``planner.<name>.*`` holds the class's own
#: constructor arguments where it has any (``pets.config.ICEMConfig``, ``MPPIConfig``).
PLANNER_CLASSES: dict[str, type[Planner]] = {"cem": CEMPlanner, "icem": ICEMPlanner, "mppi": MPPIPlanner}
