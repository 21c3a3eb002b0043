"""Planners over action sequences: CEM (as PETS uses it), iCEM and MPPI, and the MPC warm start.

All three share the API ``plan(objective, init_mean=None, generator=None) -> (H, act_dim)``: the
objective maps (N, H, act_dim) candidates to (N,) values (higher is better, NaN counts as the
worst), every sample and the result lie within the action bounds, and all randomness comes from
``generator`` (same generator state -> same plan).

Non-finite returns: candidates with a non-finite value (NaN/inf) are ranked at the bottom (CEM and
iCEM: NaN as -inf; MPPI: as the worst finite return) as long as one candidate of the iteration has
a finite value. An iteration in which *no* candidate has a finite value has nothing to rank: the
``plan`` call raises :class:`PlanningFailed` (after its iterations; the check costs one host
synchronisation per call) instead of returning what would be a random action. The trajectory
evaluator returns all-NaN exactly when every particle of every candidate went non-finite, i.e. the
model itself is broken (``pets.planning.propagation``).

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

import dataclasses
import inspect
from typing import Any

from pets.planning.planners.base import (
    BoxPlanner,
    Objective,
    Planner,
    PlanningFailed,
    check_elites_setting,
    shift_plan,
    truncated_normal,
)
from pets.planning.planners.cem import CEMPlanner
from pets.planning.planners.icem import ICEMConfig, ICEMPlanner, colored_noise
from pets.planning.planners.mppi import MPPIConfig, MPPIPlanner, smoothing_matrix

__all__ = [
    "PLANNER_CLASSES",
    "BoxPlanner",
    "CEMPlanner",
    "ICEMConfig",
    "ICEMPlanner",
    "MPPIConfig",
    "MPPIPlanner",
    "Objective",
    "Planner",
    "PlanningFailed",
    "check_planner_config",
    "colored_noise",
    "register_planner",
    "shift_plan",
    "smoothing_matrix",
    "truncated_normal",
]

#: The table of planners (``planner.name``): each name's class. The config reads it when it is used (choices, the
#: ``planner.<name>.*`` sections, their checks; ``pets.config``), so a planner registered later is accepted too.
PLANNER_CLASSES: dict[str, type[BoxPlanner]] = {}

#: What an unknown ``planner.name`` may be: a planner of one's own, registered by a module not imported here.
UNREGISTERED = (
    " (a planner of your own is known where the module that calls register_planner is imported: name that module "
    "in the config key imports, e.g. imports=[my_planner]; in a run's config.yaml: imports: [my_planner]; "
    "docs/api.md)"
)


def _check_planner(cls: object) -> None:
    """ValueError (one line) for a class that is not a complete planner: a ``BoxPlanner`` subclass with a ``name``,
    its own :meth:`~BoxPlanner.search` taking ``(objective, mu, init_mean, generator)``, and ``Options`` (and a
    ``section``, if any, with a name that is an identifier) dataclasses, ``Options`` with its ``checked()``."""
    if not (isinstance(cls, type) and issubclass(cls, BoxPlanner)) or not cls.name:
        raise ValueError(f"a planner must be a BoxPlanner subclass with a name, got {cls!r}")
    if cls.search is BoxPlanner.search:
        raise ValueError(f"planner {cls.name!r} does not implement search(objective, mu, init_mean, generator)")
    try:
        inspect.signature(cls.search).bind(None, None, None, None, None)
    except (TypeError, ValueError):
        raise ValueError(
            f"planner {cls.name!r}: search must take (self, objective, mu, init_mean, generator), "
            f"got {inspect.signature(cls.search)}"
        ) from None
    if not (dataclasses.is_dataclass(cls.Options) and isinstance(cls.Options, type)):
        raise ValueError(f"planner {cls.name!r}: Options must be a dataclass (its own arguments), got {cls.Options!r}")
    if not callable(getattr(cls.Options, "checked", None)):
        raise ValueError(f"planner {cls.name!r}: Options needs a checked() method that returns it, range-checked")
    if cls.section is not None and not (dataclasses.is_dataclass(cls.section) and isinstance(cls.section, type)):
        raise ValueError(f"planner {cls.name!r}: section must be a dataclass or None, got {cls.section!r}")
    if cls.section is not None and not cls.name.isidentifier():  # its keys planner.<name>.* are a dataclass field
        raise ValueError(
            f"planner {cls.name!r}: a planner with a section needs a name that is a Python identifier (its keys are "
            f"planner.<name>.*), e.g. {cls.name.replace('-', '_')!r}"
        )


def register_planner(cls: type[BoxPlanner]) -> type[BoxPlanner]:
    """Add ``cls`` to :data:`PLANNER_CLASSES` under ``cls.name`` (usable as a class decorator); returns it.
    ValueError for a class that is not a complete planner (:func:`_check_planner`), or a name another class holds
    (a built-in planner is never replaced behind the config's back)."""
    _check_planner(cls)
    taken = PLANNER_CLASSES.get(cls.name)
    if taken is not None and taken is not cls:
        raise ValueError(f"planner name {cls.name!r} is taken by {taken.__name__}; give {cls.__name__} another name")
    PLANNER_CLASSES[cls.name] = cls
    return cls


for _planner in (CEMPlanner, ICEMPlanner, MPPIPlanner):
    register_planner(_planner)


def check_planner_config(planner: Any) -> None:
    """The config's ``planner`` section against the table: ``planner.name`` known (a planner of one's own: see
    :data:`UNREGISTERED`), ``planner.elites`` where the planner ranks, and every planner's own section (each planner
    checks its own arguments: one range per argument); a ValueError in one line."""
    name = planner.name
    if name not in PLANNER_CLASSES:
        raise ValueError(f"planner.name must be one of {', '.join(PLANNER_CLASSES)}, got {name!r}{UNREGISTERED}")
    if PLANNER_CLASSES[name].uses_elites:
        check_elites_setting(planner.elites, planner.population)
    for other, cls in PLANNER_CLASSES.items():
        if cls.section is not None:
            try:
                cls.options(**planner[other])
            except ValueError as err:
                raise ValueError(f"planner.{other}.{err}") from None


def unknown_planner(planner: Any, schema_keys: Any) -> str | None:
    """What is wrong (from "its planner", with :data:`UNREGISTERED`) where a stored ``planner`` section (a run's
    config.yaml) names a planner the table lacks, by its ``name`` or by a sub-section that is not in ``schema_keys``
    (this process's ``planner`` keys: a process that registered a planner with a section writes that section into
    every config it makes, whatever planner the run uses); None where it names none."""
    name = str(planner.get("name", "cem"))
    sections = [key for key, value in planner.items() if hasattr(value, "keys") and key not in schema_keys]
    unknown = [name] * (name not in PLANNER_CLASSES) + [key for key in sections if key != name]
    return f"its planner {unknown[0]!r} is not a planner here{UNREGISTERED}" if unknown else None
