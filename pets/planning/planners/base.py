"""What every planner shares: the protocol, truncated-normal sampling, the MPC warm start, argument checks."""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any, ClassVar, Protocol

import torch
from torch import Tensor


class PlanningFailed(RuntimeError):
    """A plan call in which every candidate of some iteration got a non-finite return (NaN/inf): there is nothing
    to rank, so any action would be a random one. Raised instead of returning such a plan."""


def check_planned(failed: bool) -> None:
    """PlanningFailed if ``failed`` (OR-ed over the iterations of one plan call: :attr:`Objective.failed`, read
    with the plan's finiteness in the call's one host synchronisation) is true."""
    if bool(failed):
        raise PlanningFailed(
            "planning failed: every candidate action sequence got a non-finite return (nan/inf), so there is no "
            "action to choose; the dynamics model predicts non-finite states (diverged training or extreme inputs)"
        )


def no_finite(values: Tensor) -> Tensor:
    """True (bool scalar, on the device, no synchronisation) when no entry of ``values`` is finite."""
    return ~torch.isfinite(values).any()


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


def as_bounds(
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


def check_positive_ints(**values: object) -> None:
    for name, val in values.items():
        if isinstance(val, bool) or not isinstance(val, int) or val < 1:
            raise ValueError(f"{name} must be a positive int, got {val!r}")


def elite_count(elites: object, population: int) -> int:
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


def check_elites_setting(elites: float, population: int) -> None:
    """The config's ``planner.elites``: a ratio in (0, 1) of the population, or a whole count in [1, population]; a
    ValueError naming the key otherwise."""
    accepted = f"a ratio in (0, 1) of the population or a whole count in [1, planner.population={population}]"
    if elites >= 1 and elites != int(elites):
        raise ValueError(f"planner.elites must be {accepted}, got {elites:g}")
    try:
        elite_count(elites if elites < 1 else int(elites), population)
    except ValueError:
        raise ValueError(f"planner.elites must be {accepted}, got {elites:g}") from None


def check_real(
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


def check_generator(generator: torch.Generator | None, device: torch.device) -> None:
    if generator is not None and generator.device.type != device.type:
        raise ValueError(f"generator is on {generator.device}, the planner on {device}")


def initial_mean(init_mean: Tensor | None, lb: Tensor, ub: Tensor, h: int, a: int) -> Tensor:
    """The warm start clipped to the bounds, or the middle of the bounds; shape (h, a)."""
    if init_mean is None:
        return (0.5 * (lb + ub)).expand(h, a).clone()
    mu = torch.as_tensor(init_mean, device=lb.device, dtype=lb.dtype)
    if mu.shape != (h, a):
        raise ValueError(f"init_mean must have shape ({h}, {a}), got {tuple(mu.shape)}")
    return torch.minimum(torch.maximum(mu, lb), ub)


def check_values(values: Tensor, n: int, dtype: torch.dtype) -> Tensor:
    if not isinstance(values, Tensor) or values.shape != (n,):
        shape = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
        raise ValueError(f"objective must return shape ({n},), got {shape}")
    return values.to(dtype)


@dataclass
class NoOptions:
    """The own arguments of a planner that has none besides the shared ones."""

    def checked(self) -> NoOptions:
        """The arguments validated (a ValueError naming the first out of range)."""
        return self


class Objective:
    """The objective of one plan call: values (N,) in the planner's dtype, shape-checked; remembers (on the device,
    without a synchronisation) whether some call returned no finite value (``failed``)."""

    def __init__(self, fn: Callable[[Tensor], Tensor], dtype: torch.dtype, device: torch.device) -> None:
        self.fn, self.dtype = fn, dtype
        self.failed = torch.zeros((), dtype=torch.bool, device=device)

    def __call__(self, samples: Tensor) -> Tensor:
        values = check_values(self.fn(samples), samples.shape[0], self.dtype)
        self.failed = self.failed | no_finite(values)
        return values


class BoxPlanner:
    """What every planner shares: box bounds, horizon, population, iterations, smoothing ``alpha``, elites (where
    it ranks), where the samples live, and the opening and close of :meth:`plan`.

    A planner declares, as class attributes, what the rest of the code asks of it (one table entry in
    ``pets.planning.planners.PLANNER_CLASSES`` then makes it ``planner.name``): ``name``; ``Options``, the dataclass of
    its own keyword arguments (defaults, and ``checked()``, its range checks; they become attributes of the planner);
    ``section``, the dataclass of its config section ``planner.<name>.*`` (its fields are keyword arguments; None:
    no section); ``uses_elites``; ``faster``, a faster setting the cost estimate may name (``pets.planning.cost``); and
    :meth:`gain_options`, how it searches the gains of feedback candidates. It implements :meth:`search`.
    """

    name: ClassVar[str] = ""
    Options: ClassVar[type] = NoOptions
    section: ClassVar[type | None] = None
    #: Whether the constructor takes ``elites`` (the config's ``planner.elites``).
    uses_elites: ClassVar[bool] = False
    #: A setting that plans faster, with how much, for the cost estimate's line (``pets.planning.cost``); None: none.
    faster: ClassVar[str | None] = None
    #: Why the planner cannot search feedback gains (where :meth:`gain_options` is None).
    gains_note: ClassVar[str] = "it plans action sequences only"

    def __init__(
        self,
        action_low: object,
        action_high: object,
        *,
        horizon: int,
        population: int,
        iterations: int = 5,
        alpha: float = 0.1,
        elites: int | float | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
        **options: object,
    ) -> None:
        check_positive_ints(horizon=horizon, population=population, iterations=iterations)
        self.alpha = check_real("alpha", alpha, 0.0, 1.0)
        self.low, self.high = as_bounds(action_low, action_high, device, dtype)
        self.act_dim = self.low.numel()
        self.horizon = horizon
        self.population = population
        self.iterations = iterations
        self.device = self.low.device
        self.dtype = dtype
        if self.uses_elites:
            self.num_elites = elite_count(0.1 if elites is None else elites, population)
        elif elites is not None:
            raise ValueError(f"{type(self).__name__} takes no elites (it weights the whole population)")
        own = self.options(**options)
        for item in fields(own):
            setattr(self, item.name, getattr(own, item.name))
        self.setup()

    @classmethod
    def options(cls, **values: object) -> Any:
        """The planner's own arguments ``values`` as its checked ``Options``; a ValueError names an unknown one or
        the first out of range (also the config's check of ``planner.<name>.*``)."""
        known = [item.name for item in fields(cls.Options)]
        unknown = [name for name in values if name not in known]
        if unknown:
            accepted = ", ".join(known) or "none"
            raise ValueError(f"{cls.__name__} has no argument {unknown[0]!r}; its own arguments: {accepted}")
        return cls.Options(**values).checked()

    def setup(self) -> None:
        """What a planner derives from its arguments once (after they are set as attributes)."""

    @classmethod
    def gain_options(cls, gain_bound: float, gain_std: float) -> dict[str, float] | None:
        """The arguments that make it sample feedback gains in a box of +-``gain_bound`` with std ``gain_std``
        (``planner.candidates=feedback``, ``pets.planning.feedback``); None: it cannot (:attr:`gains_note` says why)."""
        return None

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
        PlanningFailed when every candidate of some iteration got a non-finite return, or :meth:`search` returned
        a plan that is not finite; ValueError for a plan of another shape than ``(H, act_dim)``.
        """
        check_generator(generator, self.device)
        mu = initial_mean(init_mean, self.low, self.high, self.horizon, self.act_dim)
        scored = Objective(objective, self.dtype, self.device)
        out = self.search(scored, mu, init_mean, generator)
        if not isinstance(out, Tensor) or out.shape != mu.shape:
            got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise ValueError(f"planner {self.name!r}: search returned {got}, not a plan of shape {tuple(mu.shape)}")
        failed, not_finite = torch.stack((scored.failed, ~torch.isfinite(out).all())).tolist()  # one synchronisation
        check_planned(failed)
        if not_finite:
            raise PlanningFailed(f"planner {self.name!r}: search returned a plan with nan or inf")
        out = self.clip(out)
        self.planned(out)
        return out

    def search(
        self, objective: Objective, mu: Tensor, init_mean: Tensor | None, generator: torch.Generator | None
    ) -> Tensor:
        """The planner's own iterations from the mean ``mu`` (the warm start ``init_mean`` clipped, or the box
        centre); returns the plan (clipped to the bounds after)."""
        raise NotImplementedError

    def planned(self, plan: Tensor) -> None:
        """What a planner keeps of a successful call for the next one (nothing here)."""

    def clip(self, x: Tensor) -> Tensor:
        """``x`` clipped to the action box."""
        return torch.minimum(torch.maximum(x, self.low), self.high)
