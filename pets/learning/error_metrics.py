"""Prediction-error metrics of one's own for ``pets.evaluate`` (:mod:`pets.learning.evaluation`).

A metric is a function (or any callable, an instance of a small class too) and one :func:`register_metric` call::

    # my_metric.py, in the folder the commands run in (or on PYTHONPATH)
    from pets.learning.evaluation import register_metric

    def max_abs_error(pred, true, layout):
        return (pred - true).abs().amax(dim=-1)

    register_metric("max_abs_error", max_abs_error)

``fn(pred, true, layout)``: the batched rollout ``pred`` and the truth ``true``, float64 tensors of shape
``(starts, steps, obs_dim)`` (``pred[:, k - 1]`` the prediction k steps after the start), and the env's
:class:`envs.layout.ObsLayout`; it returns the error of every (start, step), shape ``(starts, steps)``, and gets
copies (it may change them in place). Keep it finite where the prediction is: pets.compare offline counts a run
as diverged at a horizon where any value of its evaluation is not finite. The helpers of
:mod:`pets.learning.evaluation` take the same arguments (``step_errors``, ``entry_differences``,
``rotation_angles``, ``layout_parts``).

Named in the config key ``imports`` (``imports=[my_metric]`` given to ``pets.train``, ``run_pets.py`` or
``pets.compare offline``), the module is imported again wherever the run is loaded, ``pets.evaluate`` included,
and the metric is one more key of every horizon of ``eval.json``: like ``mean_step_error``, the mean over the
starts and over k = 1..h, shown in the table of ``pets.evaluate`` and summarised by ``pets.compare offline`` (it
summarises every ``*_error`` key, lower being better).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import TYPE_CHECKING

from pets.imports import definition

if TYPE_CHECKING:
    from torch import Tensor

    from envs.layout import ObsLayout

MetricFn = Callable[["Tensor", "Tensor", "ObsLayout"], "Tensor"]

#: The parts of an observation that get an error of their own (:func:`pets.learning.evaluation.layout_parts`).
PARTS = ("translation", "rotation", "velocity", "other", "derived")
#: The built-in error metrics per horizon (JSON keys, and the columns of the text table).
METRICS = (
    "mean_step_error",
    "final_step_error",
    *(f"{part}_error" for part in PARTS),
    "standardized_error",
)
#: Every key of a horizon's JSON entry that the library itself writes.
HORIZON_KEYS = (*METRICS, "nonfinite_fraction")
#: The metrics registered by :func:`register_metric`, by name, in the order they were registered.
METRIC_TABLE: dict[str, MetricFn] = {}

_NAME = re.compile(r"[a-z][a-z0-9_]*_error")


def register_metric(name: str, fn: MetricFn) -> MetricFn:
    """Add the error metric ``fn`` under ``name`` (its ``eval.json`` key and table column; see the module
    docstring); returns ``fn``. ValueError (one line) for a name that is not lower-case letters, digits and
    underscores ending in ``_error``, a built-in metric's (:data:`HORIZON_KEYS`), one another metric holds (the
    same function registered again, by its module imported again, is accepted), or an ``fn`` that is not
    callable."""
    if name in HORIZON_KEYS:
        raise ValueError(f"metric name {name!r} is a built-in metric of pets.evaluate; give yours another name")
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValueError(
            f"a metric's name must be lower-case letters, digits and underscores ending in _error (its eval.json key; "
            f"pets.compare offline summarises the *_error keys), e.g. max_abs_error, got {name!r}"
        )
    if not callable(fn):
        raise ValueError(f"metric {name!r} must be a callable fn(pred, true, layout), got {fn!r}")
    taken = METRIC_TABLE.get(name)
    if taken is not None and definition(taken) != definition(fn):
        raise ValueError(f"metric name {name!r} is taken (registered by {definition(taken)}); give yours another name")
    METRIC_TABLE[name] = fn
    return fn


def own_metric_names() -> tuple[str, ...]:
    """The names of the registered metrics, in the order they were registered."""
    return tuple(METRIC_TABLE)


def own_step_errors(pred: Tensor, true: Tensor, layout: ObsLayout) -> dict[str, Tensor]:
    """Each registered metric of ``pred`` against ``true`` (``(..., obs_dim)``): ``{name: (...)}`` as float64,
    each metric given its own copies of the inputs. ValueError (one line) for a metric whose value is not a
    tensor of that shape."""
    import torch

    errors = {}
    for name, fn in METRIC_TABLE.items():
        value = fn(pred.clone(), true.clone(), layout)
        if not isinstance(value, torch.Tensor) or tuple(value.shape) != tuple(pred.shape[:-1]):
            got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise ValueError(
                f"metric {name!r} ({definition(fn)}) must return a tensor of shape {tuple(pred.shape[:-1])} "
                f"(one error per start and step), got {got}"
            )
        errors[name] = value.to(torch.float64)
    return errors
