"""Your own env: an ``EnvSpec`` built from a gymnasium id, a layout and batched torch reward / termination functions,
found by name everywhere an env name is accepted (docs/api.md, "Your own env").

Two ways to name it:

- ``envs.register(spec)``: under ``spec.name``, in this process (the Python API);
- an import path ``"package.module:ATTR"`` (an ``EnvSpec``, or a function returning one), as gymnasium's entry
  points: ``run_pets.py --env package.module:ATTR`` and every other command. The run directory records the path,
  so ``--resume``, ``pets.load_model`` and ``pets.evaluate`` import it again in a new process.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
import os
import re
import sys
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor

from envs.layout import ObsLayout
from envs.spec import EnvSpec, RewardFn, gymnasium_make

_REGISTRY: dict[str, EnvSpec] = {}
#: The spec's own name of each import path in the registry (its name in file names: :func:`file_name`).
_OWN_NAMES: dict[str, str] = {}


def _never(obs: Tensor, act: Tensor, next_obs: Tensor) -> Tensor:
    return torch.zeros(obs.shape[:-1], dtype=torch.bool, device=obs.device)


def custom_spec(
    name: str,
    gym_id: str,
    layout: ObsLayout,
    reward_fn: RewardFn,
    terminated_fn: RewardFn | None = None,
    *,
    env_kwargs: Mapping[str, Any] | None = None,
    params: Mapping[str, Any] | None = None,
    episode_length: int | None = None,
    reward_differs: bool = False,
    terminated_differs: bool = False,
) -> EnvSpec:
    """An :class:`envs.EnvSpec` for the gymnasium env ``gym_id`` (built once here, to read its action bounds, time
    step and episode length, and to check the layout and the functions on real transitions).

    reward_fn, terminated_fn: batched ``(obs, act, next_obs) -> (...)`` torch functions (float reward, bool
    termination; ``None``: never terminates), for any leading dims. ValueError (one line) for a gym id gymnasium
    cannot make, a layout that does not cover the observation, functions of the wrong shape (on a small, a large
    and a 3-d batch) or that raise, and a reward that is not the env's on the real transitions (a wrong formula, or
    one that reads the wrong entries): ``reward_differs=True`` accepts a reward that differs on purpose (shaped),
    never one that is not finite; a termination that is not the env's on up to :data:`TERMINATION_STEPS` real steps
    (``None`` where the env ends episodes; ``terminated_differs=True`` accepts one that differs on purpose); a layout
    whose angles or velocities are, by the simulator's own ``qpos`` and ``qvel``, the other (:func:`check_angles`);
    and for a name that is not a non-empty string, a layout that is not an ``envs.ObsLayout`` or an
    ``episode_length`` that is not a positive int.
    """
    _check_arguments(name, layout, reward_fn, terminated_fn, episode_length)
    try:
        env = gymnasium_make(gym_id, **dict(env_kwargs or {}))
    except Exception as err:  # gymnasium's NameNotFound, DeprecatedEnv, a constructor's TypeError, ...
        raise ValueError(f"{name}: gymnasium cannot make {gym_id!r} ({type(err).__name__}: {_line(err)})") from None
    obs_space, act_space = env.observation_space, env.action_space
    if len(obs_space.shape) != 1 or len(act_space.shape) != 1:
        raise ValueError(f"{name}: only flat Box observations and actions are supported, got {obs_space}, {act_space}")
    if obs_space.shape[0] != layout.obs_dim:
        raise ValueError(
            f"{name}: the layout covers {layout.obs_dim} observation entries, {gym_id} has {obs_space.shape[0]}"
        )
    dt = float(getattr(env.unwrapped, "dt", 0.0) or 0.0)
    length = episode_length or (env.spec.max_episode_steps if env.spec and env.spec.max_episode_steps else 1000)
    try:
        probe = _real_transitions(env, act_space)
    except Exception as err:  # e.g. an env_kwargs value the constructor took but its step cannot use
        raise ValueError(f"{name}: {gym_id} failed to reset or step ({type(err).__name__}: {_line(err)})") from None
    finally:
        env.close()
    terminated_fn = terminated_fn or _never
    check_functions(name, reward_fn, terminated_fn, probe.transitions)
    check_angles(name, layout, probe)
    if not reward_differs:
        check_reward(name, gym_id, reward_fn, probe.transitions[:CHECK_STEPS])
    if not terminated_differs:
        check_termination(name, gym_id, terminated_fn, probe.transitions, given=terminated_fn is not _never)
    return EnvSpec(
        name=name,
        gym_id=gym_id,
        layout=layout,
        act_dim=int(act_space.shape[0]),
        action_low=tuple(float(x) for x in act_space.low),
        action_high=tuple(float(x) for x in act_space.high),
        dt=dt,
        episode_length=int(length),
        params=dict(params or {}),
        env_kwargs=dict(env_kwargs or {}),
        reward_error="user-defined",
        reward_fn=reward_fn,
        terminated_fn=terminated_fn,
    )


def _check_arguments(name: Any, layout: Any, reward_fn: Any, terminated_fn: Any, episode_length: Any) -> None:
    """ValueError (one line) for a custom_spec argument of the wrong kind, before gymnasium builds anything."""
    if not isinstance(name, str) or not name.strip() or any(c in name for c in ":/\\"):
        raise ValueError(f"custom_spec: name must be a non-empty string without ':', '/' or '\\', got {name!r}")
    if not isinstance(layout, ObsLayout):
        raise ValueError(f"{name}: layout must be an envs.ObsLayout, got {type(layout).__name__}")
    for what, fn in (("reward_fn", reward_fn), ("terminated_fn", terminated_fn or _never)):
        if not callable(fn):
            raise ValueError(f"{name}: {what} must be a function (obs, act, next_obs) -> tensor, got {fn!r}")
    if episode_length is not None and (
        isinstance(episode_length, bool) or not isinstance(episode_length, (int, np.integer)) or episode_length < 1
    ):
        raise ValueError(f"{name}: episode_length must be a positive int (or None: the env's), got {episode_length!r}")


#: Real transitions custom_spec checks a spec's reward on (from reset seed 0, uniformly random actions).
CHECK_STEPS = 5
#: Real transitions (the same, on until the episode ends) it checks the termination and the layout's angles on.
TERMINATION_STEPS = 200
#: Batch sizes (leading dims) the functions are checked on: a small, a large (as the planner's particles x
#: candidates) and a 3-d batch.
CHECK_BATCHES = ((2,), (10_000,), (2, 3))


def _line(err: BaseException) -> str:
    """The first line of an error's message."""
    text = str(err).strip()
    return text.splitlines()[0] if text else "no message"


@dataclasses.dataclass
class Probe:
    """Real steps of the env, from reset seed 0 with uniformly random actions, until it ends or
    :data:`TERMINATION_STEPS`: ``transitions`` ``(obs, act, next_obs, reward, terminated)`` and the simulator's
    positions and velocities after each (:func:`_state`; None where it exposes none)."""

    transitions: list[tuple]
    positions: list[np.ndarray | None]
    velocities: list[np.ndarray | None]


def _real_transitions(env: Any, act_space: Any) -> Probe:
    """The :class:`Probe` of ``env``."""
    act_space.seed(0)
    obs, _ = env.reset(seed=0)
    probe = Probe([], [], [])
    for _ in range(TERMINATION_STEPS):
        act = act_space.sample()
        nxt, reward, terminated, truncated, _ = env.step(act)
        probe.transitions.append((obs, act, nxt, float(reward), bool(terminated)))
        for out, state in zip((probe.positions, probe.velocities), _state(env)):
            out.append(state)
        if terminated or truncated:
            break
        obs = nxt
    return probe


def _state(env: Any) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The simulator's generalised positions and velocities: MuJoCo's ``qpos`` and ``qvel``; a classic-control
    env's ``state`` as its positions (Pendulum's ``[theta, theta_dot]``: the angle is among them), no velocities;
    else None."""
    inner = env.unwrapped
    data = getattr(inner, "data", None)
    if data is not None and hasattr(data, "qpos"):
        return _flat(data.qpos), _flat(getattr(data, "qvel", None))
    return _flat(getattr(inner, "state", None)), None


def _flat(state: Any) -> np.ndarray | None:
    try:
        return None if state is None else np.array(state, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None


def check_functions(name: str, reward_fn: RewardFn, terminated_fn: RewardFn, transitions: list[tuple]) -> None:
    """ValueError (one line) for a reward or termination function that raises, or returns anything but a float
    (reward) or bool (termination) tensor of the inputs' leading dims, on each batch of :data:`CHECK_BATCHES`."""
    obs, act, nxt = transitions[0][:3]
    for batch in CHECK_BATCHES:
        o, a, n = (torch.as_tensor(x, dtype=torch.float32).expand(*batch, len(x)).contiguous() for x in (obs, act, nxt))
        for what, fn, kind in (("reward_fn", reward_fn, "float"), ("terminated_fn", terminated_fn, "bool")):
            try:
                out = fn(o, a, n)
            except Exception as err:
                raise ValueError(
                    f"{name}: {what} raised {type(err).__name__} on inputs of shape {tuple(o.shape)}: {_line(err)}"
                ) from None
            if not isinstance(out, Tensor) or out.shape != batch:
                shape = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
                raise ValueError(
                    f"{name}: {what} must return a tensor of shape (batch,) for (batch, dim) inputs (any leading "
                    f"dims), got {shape} for inputs of shape {tuple(o.shape)}"
                )
            if kind == "bool" and out.dtype != torch.bool:
                raise ValueError(f"{name}: terminated_fn must return a bool tensor, got {out.dtype}")
            if kind == "float" and not out.is_floating_point():
                raise ValueError(f"{name}: reward_fn must return a float tensor, got {out.dtype}")
            if kind == "float" and not torch.isfinite(out).all():
                raise ValueError(f"{name}: reward_fn returned nan or inf on a real transition; a reward must be finite")


def check_angles(name: str, layout: ObsLayout, probe: Probe) -> None:
    """ValueError (one line) where, on the real steps of ``probe``, an ``SO2_cossin`` group's entries are not a
    cosine and a sine (``cos^2 + sin^2`` off 1) or are swapped, or an angle and a velocity of the layout are the
    other (:func:`check_kinds`).

    A swap keeps ``cos^2 + sin^2 = 1`` and any reward that reads the observation directly, but decodes the angle
    ``atan2(cos, sin) = pi/2 - theta``. Checked against the simulator's own positions after each transition
    (MuJoCo's ``qpos``): refused where the swapped reading equals one of them (mod 2 pi) on every transition and the
    stated reading equals none. Where the env exposes no positions, or neither reading matches (an angle the
    simulator does not hold as a coordinate), nothing is decided.
    """
    nxt = np.array([t[2] for t in probe.transitions], dtype=np.float64)
    q = _stacked(probe.positions)
    for group in layout.groups_of("SO2_cossin"):
        c, s = group.indices
        norm = np.hypot(nxt[:, c], nxt[:, s])
        if not np.allclose(norm, 1.0, atol=1e-3):
            raise ValueError(
                f"{name}: group {group.name!r} (SO2_cossin, entries {c}, {s}) is not a cosine and a sine on real "
                f"observations (cos^2 + sin^2 = {float(norm.min() ** 2):.3g}..{float(norm.max() ** 2):.3g}, not 1)"
            )
        if q is not None and _matches(q, np.arctan2(nxt[:, c], nxt[:, s]), True) is not None:
            if _matches(q, np.arctan2(nxt[:, s], nxt[:, c]), True) is None:
                raise ValueError(
                    f"{name}: group {group.name!r} (SO2_cossin) reads its angle the wrong way round: the simulator's "
                    f"angle is atan2(obs[{c}], obs[{s}]), so its indices (cos_index, sin_index) are ({s}, {c}), "
                    f"not ({c}, {s})"
                )
    check_kinds(name, layout, nxt, q, _stacked(probe.velocities))


def check_kinds(name: str, layout: ObsLayout, nxt: np.ndarray, q: np.ndarray | None, v: np.ndarray | None) -> None:
    """ValueError (one line) where an ``SO2_angle`` entry is, on every real step, one of the simulator's velocities
    ``v`` (``qvel``) and none of its positions ``q``, or a ``velocities`` entry one of its positions and none of its
    velocities: a layout with an angle and a velocity swapped. Only positive evidence decides (a clipped or derived
    entry matches neither and passes)."""
    if q is None or v is None:
        return
    for group in layout.groups_of("SO2_angle"):
        for i in group.indices:
            j = _matches(v, nxt[:, i], False)
            if j is not None and _matches(q, nxt[:, i], True) is None:
                raise ValueError(
                    f"{name}: group {group.name!r} (SO2_angle) reads entry {i}, which is the simulator's velocity "
                    f"qvel[{j}] on real steps, not an angle: check the layout's indices"
                )
    for i in layout.velocities:
        j = _matches(q, nxt[:, i], False)
        if j is not None and _matches(v, nxt[:, i], False) is None:
            raise ValueError(
                f"{name}: the layout's velocities include entry {i}, which is the simulator's position qpos[{j}] on "
                "real steps, not a velocity: check the layout's indices (a position that is not an angle belongs in "
                "an Rn group, or in other)"
            )


def _stacked(states: list[np.ndarray | None]) -> np.ndarray | None:
    """``states`` as (steps, n), or None where a step has none or their sizes differ."""
    if not states or any(x is None or len(x) != len(states[0]) for x in states):
        return None
    return np.stack(states)


def _matches(columns: np.ndarray, value: np.ndarray, angle: bool) -> int | None:
    """The first column of ``columns`` (steps, n) that equals ``value`` (steps,) on every step to 1e-3 (``angle``:
    mod 2 pi), or None."""
    diff = columns - value[:, None]
    gap = np.abs(np.angle(np.exp(1j * diff))) if angle else np.abs(diff)
    hit = np.flatnonzero((gap < 1e-3).all(axis=0))
    return int(hit[0]) if hit.size else None


def _raised_in_float64(name: str, what: str, err: BaseException) -> str:
    return (
        f"{name}: {what} raised {type(err).__name__} on real transitions in float64 (the checks compare it with the "
        f"env's there; make it work in any float dtype): {_line(err)}"
    )


def check_reward(name: str, gym_id: str, reward_fn: RewardFn, transitions: list[tuple]) -> None:
    """ValueError (one line) where ``reward_fn`` is not the env's reward on the real ``transitions`` (to 1e-3
    relative and absolute, the observations being float32)."""
    for step, (obs, act, nxt, want, _) in enumerate(transitions):
        o, a, n = (torch.as_tensor(x, dtype=torch.float64)[None] for x in (obs, act, nxt))
        try:
            got = float(reward_fn(o, a, n)[0])
        except Exception as err:
            raise ValueError(_raised_in_float64(name, "reward_fn", err)) from None
        if not abs(got - want) <= 1e-3 * (1.0 + abs(want)):
            raise ValueError(
                f"{name}: reward_fn gives {got:.6g} where {gym_id} gave {want:.6g} on a real transition (step {step} "
                "from reset seed 0): check the layout (entries swapped?) and the formula, or pass "
                "reward_differs=True for a reward that differs from the env's on purpose"
            )


def check_termination(name: str, gym_id: str, terminated_fn: RewardFn, transitions: list[tuple], given: bool) -> None:
    """ValueError (one line) where ``terminated_fn`` is not the env's termination on the real ``transitions`` (the
    first step where they differ; ``given``: False where no function was given, read as never terminating)."""
    o, a, n = (torch.as_tensor(np.stack([t[k] for t in transitions]), dtype=torch.float64) for k in range(3))
    want = np.array([t[4] for t in transitions])
    try:
        got = terminated_fn(o, a, n).cpu().numpy().astype(bool)
    except Exception as err:
        raise ValueError(_raised_in_float64(name, "terminated_fn", err)) from None
    wrong = np.flatnonzero(got != want)
    if wrong.size:
        k = int(wrong[0])
        what = "terminated_fn" if given else "no terminated_fn (never terminates)"
        says, did = ("ends", "went on") if got[k] else ("goes on", "ended")
        raise ValueError(
            f"{name}: {what} says the episode {says} where {gym_id} {did} on a real transition (step {k} from reset "
            "seed 0, random actions): give the env's termination as terminated_fn, or pass terminated_differs=True "
            "for one that differs on purpose"
        )


def check_dims(spec: EnvSpec) -> None:
    """ValueError (one line) where a spec's observation or action size is not its gymnasium env's (a hand-built
    ``EnvSpec``; ``custom_spec`` reads them from the env)."""
    try:
        env = spec.make()
    except Exception as err:
        raise ValueError(
            f"{spec.name}: gymnasium cannot make {spec.gym_id!r} ({type(err).__name__}: {_line(err)})"
        ) from None
    obs_shape, act_shape = env.observation_space.shape, env.action_space.shape
    env.close()
    if obs_shape != (spec.obs_dim,) or act_shape != (spec.act_dim,):
        raise ValueError(
            f"{spec.name}: the spec says obs_dim {spec.obs_dim} and act_dim {spec.act_dim}, {spec.gym_id} has "
            f"observations {obs_shape} and actions {act_shape}; build it with envs.custom_spec, which reads them"
        )


def file_name(name: str) -> str:
    """The name of env ``name`` in file and directory names: an import path ``module:ATTR`` (whose colon breaks
    scp, rsync, Windows and TensorBoard's ``name:path``) by its spec's own name, other names as they are."""
    if ":" not in name:
        return name
    if name not in _OWN_NAMES:
        try:
            registered(name)
        except ValueError:  # not importable here: the attribute's name
            pass
    own = _OWN_NAMES.get(name) or name.partition(":")[2]
    return re.sub(r"[^A-Za-z0-9._+-]", "-", own) or "env"


def register(spec: EnvSpec) -> EnvSpec:
    """Make ``spec`` an env name (``spec.name``) in this process; returns it. A catalogue name, or a name another
    spec holds, cannot be taken (a run records its env by name: one name, one env)."""
    from envs.catalogue import GYM_IDS, catalogue_key

    if not isinstance(spec, EnvSpec):
        raise ValueError(f"register takes an envs.EnvSpec, got {type(spec).__name__}")
    key = catalogue_key(spec.name)
    if key is not None:
        raise ValueError(
            f"{spec.name!r} names the catalogue env {key} ({GYM_IDS[key]}); register yours under another name"
        )
    taken = _REGISTRY.get(spec.name)
    if taken is not None and taken is not spec:
        raise ValueError(
            f"env name {spec.name!r} is registered to another spec in this process; give yours another name"
        )
    check_dims(spec)
    _REGISTRY[spec.name] = spec
    return spec


def registered(name: str) -> EnvSpec | None:
    """The spec registered or importable as ``name`` (an import path ``module:ATTR`` is imported and registered
    under that path), else None."""
    if name in _REGISTRY:
        return _REGISTRY[name]
    if ":" not in name:
        return None
    module, _, attr = name.partition(":")
    user_folder_importable()
    try:
        imported = importlib.import_module(module)
    except ModuleNotFoundError as err:
        raise ValueError(
            f"env {name}: cannot import {attr!r} from {module!r} ({err}); run the command from the folder that holds "
            f"{module.split('.')[0]}.py (or put that folder on PYTHONPATH)"
        ) from None
    except ImportError as err:
        raise ValueError(f"env {name}: cannot import {attr!r} from {module!r} ({_line(err)})") from None
    except Exception as err:  # the module raised on import: a RuntimeError, a SyntaxError, a failed custom_spec
        raise ValueError(f"env {name}: importing {module!r} failed ({type(err).__name__}: {_line(err)})") from None
    if not hasattr(imported, attr):
        close = difflib.get_close_matches(attr, [n for n in dir(imported) if not n.startswith("_")], n=1)
        hint = f"; did you mean {module}:{close[0]}?" if close else ""
        raise ValueError(f"env {name}: cannot import {attr!r} from {module!r} (it has no such name{hint})")
    found: Any = getattr(imported, attr)
    if isinstance(found, Callable) and not isinstance(found, EnvSpec):
        try:
            spec = found()
        except Exception as err:
            raise ValueError(f"env {name}: {attr}() raised {type(err).__name__}: {_line(err)}") from None
        if not isinstance(spec, EnvSpec):
            raise ValueError(f"env {name}: {attr}() returned a {type(spec).__name__}, not an envs.EnvSpec")
    else:
        spec = found
    if not isinstance(spec, EnvSpec):
        kind = type(spec).__name__
        raise ValueError(f"env {name}: {attr} is of type {kind}, not an envs.EnvSpec (or a function returning one)")
    check_dims(spec)
    _OWN_NAMES[name] = spec.name
    spec = dataclasses.replace(spec, name=name)  # the path is the name a run directory records
    _REGISTRY[name] = spec
    return spec


def user_folder_importable() -> None:
    """Put the current folder on ``sys.path`` (last) if it is not there, so that ``--env mymodule:SPEC`` imports
    ``mymodule.py`` from where the user runs any command, as ``python -m`` would (``python run_pets.py`` and console
    scripts put only their own folder there); child processes get it through :func:`child_environment`."""
    cwd = os.getcwd()
    if "" not in sys.path and cwd not in sys.path:
        sys.path.append(cwd)


def child_environment(env: Mapping[str, str] | None = None) -> dict[str, str]:
    """``env`` (default: this process's environment) with the current folder added to PYTHONPATH, for a child
    process that starts elsewhere (pets.compare's runs start in the repository) and imports the user's env."""
    env = dict(os.environ if env is None else env)
    parts = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    env["PYTHONPATH"] = os.pathsep.join([*parts, os.getcwd()] if os.getcwd() not in parts else parts)
    return env
