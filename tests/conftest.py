import os
import sys
from pathlib import Path

import pytest
import torch

import envs.custom
from pets.runs import hardware
from tests.threads import one_thread

ROOT = Path(__file__).resolve().parents[1]

#: The real threshold of ``model.compile=auto`` (pets.runs.hardware), for the tests of auto itself.
AUTO_COMPILE_MIN_TRIALS = hardware.AUTO_COMPILE_MIN_TRIALS


def pytest_configure(config):
    """Under pytest-xdist (the README's ``-n 2``) each worker gets its share of the cores for torch, so that the
    workers' thread pools do not oversubscribe them."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers:
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // int(workers)))


@pytest.fixture(autouse=True)
def env_names_end_with_their_test():
    """Env names a test registers (``envs.register``, docs/api.md's examples, ``module:ATTR`` paths) are gone after
    it, so that no test sees another's: a name such as "pendulum" stays unknown to the tests that expect it so."""
    before = dict(envs.custom._REGISTRY)
    yield
    envs.custom._REGISTRY.clear()
    envs.custom._REGISTRY.update(before)


@pytest.fixture(autouse=True)
def planner_model_and_codec_names_end_with_their_test():
    """Planners, models, codec kinds, propagation modes, candidate kinds and error metrics a test registers
    (``register_planner``, ``register_model``, ``register_codec``, ``register_propagation``, ``register_candidates``,
    ``register_metric``, a module of the config key ``imports`` such as tests/own_planner.py or tests/own_codec.py)
    are gone after it, and a module imported by the test that registered them is forgotten (a later ``imports`` of
    it registers them again): no test sees another's names."""
    from envs.layout import KIND_WIDTH
    from gem_head.codecs import _ADDED_KINDS, CODECS
    from pets.learning.error_metrics import METRIC_TABLE
    from pets.models import MODELS
    from pets.planning.particles import CANDIDATE_TABLE, PROPAGATION_TABLE
    from pets.planning.planners import PLANNER_CLASSES

    tables = (PLANNER_CLASSES, MODELS, CODECS, KIND_WIDTH, PROPAGATION_TABLE, CANDIDATE_TABLE, METRIC_TABLE)
    before, added, modules = [dict(table) for table in tables], set(_ADDED_KINDS), set(sys.modules)
    yield
    registered = any(table.keys() != old.keys() for table, old in zip(tables, before, strict=True))
    for table, old in zip(tables, before, strict=True):
        table.clear()
        table.update(old)
    _ADDED_KINDS.intersection_update(added)
    if registered:  # forget the user's modules imported during the test only (a model may reuse a built-in head,
        for name in set(sys.modules) - modules:  # so its entry does not name its module); never another test's
            if _users_module(sys.modules.get(name)):
                sys.modules.pop(name, None)


def _users_module(module: object) -> bool:
    """A module of a user's folder or of tests/ (not the library's, nor an installed or standard one)."""
    path = str(getattr(module, "__file__", None) or "")
    library = [str(ROOT / package) for package in ("pets", "envs", "gem_head", "dynamics")]
    return (
        bool(path)
        and "site-packages" not in path
        and not path.startswith(sys.base_prefix)
        and not any(path.startswith(folder) for folder in library)
    )


@pytest.fixture
def single_thread():
    """Run the test with one torch thread (see tests/threads.py)."""
    with one_thread():
        yield


@pytest.fixture(scope="session", autouse=True)
def eager_training_for_auto():
    """The fast preset's ``model.compile=auto`` compiles training (inductor) for runs of >= 10 trials on CPUs with
    native bf16. The suite's runs are tiny: each would pay the compile and not get it back, so here ``auto`` trains
    eagerly; tests that ask for ``model.compile=true`` still compile, and the tests of auto use
    :func:`real_auto_compile`. (Session scope: the module fixtures' runs are made under it too.)"""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(hardware, "AUTO_COMPILE_MIN_TRIALS", 10**9)
        yield


@pytest.fixture
def real_auto_compile(monkeypatch):
    """``model.compile=auto`` with its real threshold (see :func:`eager_training_for_auto`)."""
    monkeypatch.setattr(hardware, "AUTO_COMPILE_MIN_TRIALS", AUTO_COMPILE_MIN_TRIALS)
