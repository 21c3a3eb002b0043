"""The configuration's defaults below the command line: per-env research defaults, per-model defaults, the
presets and their per-env amendments. :func:`pets.config.make_config` applies them in the order ``Config``
defaults -> ``ENV_DEFAULTS[env]`` -> ``PRESETS[preset]`` -> ``PRESET_ENV_DEFAULTS[(preset, env)]`` ->
``head_defaults(head)`` -> ``key=value`` overrides."""

from __future__ import annotations

from typing import Any

from pets.models import MODELS

# Per-env research defaults, following PETS (Chua et al., 2018) and its well-known implementations; envs without a
# published PETS config borrow the nearest one (IDP from InvertedPendulum, Walker2d from Hopper,
# Ant and Humanoid from HalfCheetah).
_HALFCHEETAH = {"trials": 300, "planner": {"horizon": 30, "population": 400, "elites": 0.16, "particles": 20}}
_HOPPER = {"trials": 300, "planner": {"horizon": 30, "population": 350, "elites": 0.1, "particles": 20}}
_PENDULUM = {"trials": 20, "planner": {"horizon": 45, "population": 480, "elites": 0.078, "particles": 20}}
ENV_DEFAULTS: dict[str, dict[str, Any]] = {
    "invertedpendulum": _PENDULUM,
    "inverteddoublependulum": _PENDULUM,
    "reacher": {"trials": 100, "planner": {"horizon": 15, "population": 350, "elites": 0.1, "particles": 20}},
    "hopper": _HOPPER,
    "walker2d": _HOPPER,
    "halfcheetah": _HALFCHEETAH,
    "ant": _HALFCHEETAH,
    "humanoid": _HALFCHEETAH,
}


def head_defaults(head: str) -> dict[str, Any]:
    """Per-model defaults, read from the model table when the config is made (a model registered from ``imports``
    too): a deterministic model (delta-det, gem2) averages its members' predictions, as the paper's ensembles do,
    which is PETS' expectation propagation (pets.models explains; tsinf also works)."""
    entry = MODELS.get(head)
    return {"planner": {"propagation": "expectation"}} if entry is not None and entry.deterministic else {}


# A CPU-friendly preset: ~20x fewer model evaluations per planning step than the research defaults.
PRESETS: dict[str, dict[str, Any]] = {
    "research": {},
    "fast": {
        # model.compile auto: the compiled training step where it was measured ~2x faster (pets.runs.hardware)
        "model": {"ensemble_size": 5, "num_elites": 5, "batch_size": 32, "compile": None},
        "planner": {"population": 100, "particles": 5, "horizon": 15, "iterations": 3, "elites": 0.1},
    },
    # PETS that learns locomotion within a 100k env-step budget on a 2-core CPU (issue 56; docs/studies/
    # locomotion_gate.md): the fast planner (its settings checked with the true dynamics, pets.oracle), a learned
    # terminal value on every env, and a fixed training schedule by env steps (warm-started, a fixed number of
    # gradient steps every 1,000 env steps: the cost of training does not grow with the data or the falls).
    "locomotion": {
        "trials": 100_000,  # an upper bound: the budget ends the run
        "max_env_steps": 100_000,
        "seed_steps": 1000,
        "train_every": 1000,
        "train_after_trial": False,
        "model": {"ensemble_size": 5, "num_elites": 5, "batch_size": 256, "iterations": 1000, "compile": None},
        "planner": {  # CEM, not iCEM: chosen with the true dynamics (docs/studies/locomotion_gate.md, pilots)
            "name": "cem",
            "population": 100,
            "particles": 5,
            "horizon": 15,
            "iterations": 3,
            "elites": 0.1,
        },
        "value": {"enabled": True},
    },
}

# InvertedDoublePendulum: open-loop sequences that keep it up for the horizon are too rare to sample, even with
# the true dynamics; linear state-feedback candidates (the cart position, the two sines and the three velocities,
# fixed scales) rolled out for 3 s balance it, with the simulator and with the learned model (docs/planning.md).
_IDP_FEEDBACK = {
    "planner": {
        "name": "cem",
        "candidates": "feedback",
        "horizon": 60,
        "propagation": "members",
        "feedback": {"features": [0, 1, 2, 5, 6, 7], "scale": [0.5, 0.2, 0.2, 1.0, 2.0, 2.0]},
    }
}

# Per-env amendments to a preset. The pendulums' reward is a flat "alive" bonus: every candidate that
# survives the horizon ties, so CEM's elite mean of a small population is noise and the cart runs into
# its rail. MPPI averages the whole population and is measured to balance (docs/results.md). On
# InvertedPendulum the cart still drifts into the end of its rail, beyond any horizon open-loop plans can
# predict; a learned terminal value and a smaller MPPI noise keep it near the centre (docs/planning.md).
PRESET_ENV_DEFAULTS: dict[tuple[str, str], dict[str, Any]] = {
    ("fast", "invertedpendulum"): {
        "planner": {"name": "mppi", "horizon": 20, "mppi": {"sigma": 0.2}},
        "value": {"enabled": True},
    },
    ("fast", "inverteddoublependulum"): _IDP_FEEDBACK,
}
