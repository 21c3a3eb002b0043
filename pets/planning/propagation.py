"""Trajectory sampling through a probabilistic ensemble (PETS, Chua et al. 2018).

A :class:`TrajectoryEvaluator` scores N candidate action sequences from one start
observation: each candidate is rolled out as P particles through the learned model,
rewards are summed over the horizon and averaged over the particles.

Propagation modes (``PROPAGATIONS``):

- ``ts1``: every particle re-draws its ensemble member at every step. As in PETS this is
  done with a fresh random permutation of all rows per step, so that every member gets
  the same number of rows (each row's member is uniform over the members).
- ``tsinf``: every particle keeps one member for the whole horizon. Particle ``p`` of
  candidate ``n`` uses member ``(n * P + p) % M``: the particles of one candidate cycle
  through the members (exactly ``P / M`` particles per member when ``M`` divides ``P``).
  The assignment is deterministic; candidates are i.i.d. samples of the planner, so a
  candidate's index carries no information and this adds no bias between candidates.
- ``members``: as ``tsinf`` (each particle keeps one member) but without the Gaussian sampling: a particle
  follows its member's predicted mean, so the particles of a candidate differ only where the members disagree
  (the epistemic spread, without the aleatoric noise). Deterministic.
- ``expectation``: no sampling; the next target is the mean over the members' predicted
  means (taken in target space, before ``head.next_obs``). All particles would be
  identical, so each candidate is rolled out once.

Sampling: ``target = mean + exp(0.5 * logvar) * eps`` with ``eps ~ N(0, I)`` drawn from the
given generator, then ``next_obs = head.next_obs(obs, target)``.

Vectorised layout: the rows (N * P, padded up to a multiple of M with dummy rows that are
dropped at the end) are arranged member-major, so the ensemble gets one ``(M, B / M, in)``
input per step (one batched GEMM per layer). For ``tsinf`` the layout is fixed for the whole
rollout (no gather per step); for ``ts1`` rows are gathered into a fresh random permutation
before the model and scattered back after. Each mode is a row layout and a noise, and each candidate kind
(``CANDIDATES``: action sequences or feedback gains) a strategy, that the evaluator composes
(``pets.planning.particles``). The only Python loop is over the horizon and
there is no host synchronisation inside it.

Terminations and the non-finite guard: ``terminated_fn(obs, act, next_obs)`` marks a row
done; the reward of the terminating transition counts, later rewards are zero and the state
is frozen (a terminated state is absorbing). A transition whose predicted next state or
reward is not finite (NaN/inf, e.g. a diverging model; also a state whose values are finite but sum
beyond float32's range, ~3e38: one row sum is the check) is treated as a termination whose
reward is ``nonfinite_reward`` (default -1e6) instead of the (non-finite) reward, so the
planner gets finite returns that rank such candidates at the bottom (a row that diverges later
is still ranked by the finite rewards before it). The one exception: when the *first* transition
of every row (every particle of every candidate) is non-finite, the model predicts nothing finite
from the current state (e.g. NaN weights), no return means anything, so every return is NaN
(decided on the device, no synchronisation) and the planner raises
``pets.planning.planners.PlanningFailed`` rather than act at random.

Speed options (both off by default; see docs/performance.md for measured figures):

- ``precision="bf16"``: the ensemble forward runs under ``torch.autocast(bfloat16)``, so its
  matmuls run in bfloat16 (about 2.5x the fp32 GEMM throughput on CPUs with AVX-512 bf16 and
  on recent GPUs). Its outputs are cast back to float32 at once: the state, the sampling
  noise, the Gaussian sampling, the rewards and the returns stay float32. The predicted
  means carry bfloat16 rounding (relative 2^-9), so returns differ from fp32 by a small
  relative amount (tested on a model trained on real HalfCheetah data).
- ``compile=True``: the whole rollout step (head inputs, ensemble forward, Gaussian sampling,
  ``head.next_obs``, reward, termination, non-finite guard) is compiled with
  ``torch.compile``; the random draws (permutation, noise) stay outside it, in the same order
  as the eager path, so compiled and eager returns agree to float rounding. A failure to
  compile (e.g. no C++ compiler) warns once and falls back to eager for good.

The eager float32 path performs exactly the operations it always did (same generator
stream, bit-identical returns); per-call buffers (time-major actions, one noise buffer
refilled in place) remove the per-step strided action reads and noise allocations.
"""

from __future__ import annotations

import ctypes
import math
import sys
import warnings
from collections.abc import Callable

import torch
from torch import Tensor

from dynamics import fused
from dynamics.model import DynamicsModel
from pets.planning.feedback import LinearFeedback
from pets.planning.particles import CANDIDATE_TABLE, PROPAGATION_TABLE, FeedbackGains, OpenLoop
from pets.runs.hardware import CONCRETE_PRECISIONS as PRECISIONS

#: ``planner.propagation``: how particles go through the ensemble (the module docstring; ``pets.planning.particles``);
#: a live view of the table, so a mode added by ``register_propagation`` (``imports``) is accepted too.
PROPAGATIONS = PROPAGATION_TABLE.keys()
#: ``planner.candidates``: what a planner's candidate is, an action sequence (PETS) or the gains of a linear
#: feedback law (``pets.planning.feedback``; ``pets.planning.particles``); a live view of the table, so a kind added
#: by ``register_candidates`` (``imports``) is accepted too (the evaluator rolls out the kind the builder made).
CANDIDATES = CANDIDATE_TABLE.keys()

#: ``fn(obs, act, next_obs) -> (...,)`` batched torch reward / termination function.
TransitionFn = Callable[[Tensor, Tensor, Tensor], Tensor]

_MALLOC_TUNED: bool | None = None


def retain_freed_memory() -> bool:
    """Let glibc keep freed CPU memory for reuse instead of handing it back to the OS (process-wide, idempotent).

    A rollout step allocates and frees the same few MB-sized activations every step. With glibc's
    defaults such blocks are either fresh ``mmap``s or trimmed off the top of the heap when freed, so
    every step pays page faults on memory the kernel must zero again (~30k faults per evaluator call
    at the PETS HalfCheetah sizes). ``mallopt(M_MMAP_THRESHOLD, 32 MiB)`` (glibc's maximum) and
    ``mallopt(M_TRIM_THRESHOLD, 1 GiB)`` keep them in the heap: eager fp32 rollouts run ~15-20%
    faster on CPU (docs/performance.md), with bit-identical results. The price: the resident size no
    longer shrinks after a peak. Returns whether the settings are in effect (False where glibc's
    ``mallopt`` is unavailable, e.g. macOS or musl).
    """
    global _MALLOC_TUNED
    if _MALLOC_TUNED is None:
        _MALLOC_TUNED = False
        if sys.platform.startswith("linux"):
            try:
                libc = ctypes.CDLL(None)
                m_trim_threshold, m_mmap_threshold = -1, -3
                ok = libc.mallopt(m_mmap_threshold, 32 << 20) == 1
                ok = libc.mallopt(m_trim_threshold, 1 << 30) == 1 and ok
                _MALLOC_TUNED = ok
            except (OSError, AttributeError):
                pass
    return _MALLOC_TUNED


class TrajectoryEvaluator:
    """Scores action sequences by trajectory sampling through a dynamics model.

    model: a :class:`dynamics.model.DynamicsModel` (``inputs``, ``forward(x, members) -> (mean, logvar)``,
      ``next_obs``, ``elites``).
    reward_fn, terminated_fn: batched ``(obs, act, next_obs) -> (...,)``; ``terminated_fn``
      may be ``None`` (never terminates).
    particles: particles per candidate (P).
    propagation: one of ``PROPAGATIONS``.
    use_elites: propagate through the elite members only (else through all members).
    nonfinite_reward: reward given to a transition into a non-finite state (then terminated).
    precision: ``fp32`` or ``bf16`` (ensemble matmuls under bfloat16 autocast, all else float32).
    compile: compile the rollout step with ``torch.compile`` (eager fallback on failure).
    compile_backend: the ``torch.compile`` backend (``inductor`` generates fused C++/Triton kernels; the
      tests use ``aot_eager``, which traces the same graph without code generation).
    terminal_value: ``V(obs) -> (...)``, added to the return of every row that did not terminate, at its final
      state (``pets.planning.value``); None: the horizon rewards only.
    termination_penalty: subtracted from the return of every row that terminated within the horizon (>= 0; 0:
      a termination only ends the rewards, as in PETS). It ranks a candidate predicted to fall below one that
      does not, however much faster it moves before the fall.
    risk_aversion: k >= 0; a candidate's return is the mean over its particles minus k times their standard
      deviation (population form), a pessimism against the model's spread that ranks a candidate whose particles
      disagree (some fall, some run) below one whose particles agree; 0: the mean, as in PETS. Inert where the
      particles cannot differ (``expectation``, or one particle).
    feedback: a :class:`pets.planning.feedback.LinearFeedback`: candidates are then gains (N, rows, act_dim), rolled out
      for ``feedback.horizon`` steps with each particle's action computed from its own predicted state; None:
      candidates are action sequences (N, H, act_dim).
    candidates: the candidate kind's strategy (an instance of a class of ``pets.planning.particles.CANDIDATE_TABLE``,
      its law its ``law``), instead of ``feedback``; None: :class:`~pets.planning.particles.FeedbackGains` of
      ``feedback``, or :class:`~pets.planning.particles.OpenLoop` without one.
    """

    def __init__(
        self,
        model: DynamicsModel,
        reward_fn: TransitionFn,
        terminated_fn: TransitionFn | None,
        *,
        particles: int = 20,
        propagation: str = "tsinf",
        use_elites: bool = True,
        nonfinite_reward: float = -1e6,
        precision: str = "fp32",
        compile: bool = False,
        compile_backend: str = "inductor",
        terminal_value: Callable[[Tensor], Tensor] | None = None,
        termination_penalty: float = 0.0,
        risk_aversion: float = 0.0,
        feedback: LinearFeedback | None = None,
        candidates: OpenLoop | None = None,
    ) -> None:
        if candidates is not None and (feedback is not None or not isinstance(candidates, OpenLoop)):
            raise ValueError(f"candidates must be a candidate kind (an OpenLoop) without feedback, got {candidates!r}")
        if propagation not in PROPAGATIONS:
            raise ValueError(f"unknown propagation {propagation!r}; accepted: {', '.join(PROPAGATIONS)}")
        if isinstance(particles, bool) or not isinstance(particles, int) or particles < 1:
            raise ValueError(f"particles must be a positive int, got {particles!r}")
        if not callable(reward_fn):
            raise ValueError("reward_fn must be callable as reward_fn(obs, act, next_obs)")
        if terminated_fn is not None and not callable(terminated_fn):
            raise ValueError("terminated_fn must be None or callable as terminated_fn(obs, act, next_obs)")
        self.model = model
        self.reward_fn = reward_fn
        self.terminated_fn = terminated_fn
        self.particles = particles
        self.propagation = propagation
        self.use_elites = use_elites
        self.nonfinite_reward = float(nonfinite_reward)
        if precision not in PRECISIONS:
            raise ValueError(f"unknown precision {precision!r}; accepted: {PRECISIONS}")
        if not isinstance(compile, bool):
            raise ValueError(f"compile must be a bool, got {compile!r}")
        self.precision = precision
        self.compile = compile
        self.compile_backend = compile_backend
        self.terminal_value = terminal_value
        if not math.isfinite(termination_penalty) or termination_penalty < 0:
            raise ValueError(f"termination_penalty must be a finite number >= 0, got {termination_penalty!r}")
        self.termination_penalty = float(termination_penalty)
        if not math.isfinite(risk_aversion) or risk_aversion < 0:
            raise ValueError(f"risk_aversion must be a finite number >= 0, got {risk_aversion!r}")
        self.risk_aversion = float(risk_aversion)
        if candidates is None:
            candidates = OpenLoop() if feedback is None else FeedbackGains(feedback)
        self.feedback = candidates.law
        self._propagation = PROPAGATION_TABLE[propagation]
        self._candidates = candidates
        self._compiled_step: Callable | None = None
        self._compile_failed = False

    # ------------------------------------------------------------------ helpers
    def members(self, device: torch.device) -> Tensor | None:
        """Member indices propagated through (``None``: all members, in order).

        The model's elites when ``use_elites``.
        """
        if not self.use_elites:
            return None
        return self.model.elites.to(device=device, dtype=torch.long)

    def _num_members(self, members: Tensor | None) -> int:
        return int(self.model.ensemble_size) if members is None else members.numel()

    def model_rows(self, candidates: int, device: torch.device) -> int:
        """(row, member) pairs one model step of ``candidates`` candidates computes (its propagation's layout)."""
        m = self._num_members(self.members(device))
        return self._propagation.layout.model_rows(candidates, self.particles, m)

    def _check(self, obs0: Tensor, actions: Tensor, generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
        if not isinstance(actions, Tensor) or actions.dim() != 3:
            shape = tuple(actions.shape) if isinstance(actions, Tensor) else type(actions).__name__
            raise ValueError(f"actions must be a tensor of shape (N, H, act_dim), got {shape}")
        if actions.shape[0] < 1 or actions.shape[1] < 1:
            raise ValueError(f"actions must have N >= 1 candidates and H >= 1 steps, got shape {tuple(actions.shape)}")
        act_dim = self.model.act_dim
        if actions.shape[2] != act_dim:
            raise ValueError(f"actions have act_dim {actions.shape[2]}, the model expects {act_dim}")
        self._candidates.check(actions)
        if not actions.is_floating_point():
            actions = actions.float()
        obs0 = torch.as_tensor(obs0, device=actions.device, dtype=actions.dtype)
        obs_dim = self.model.obs_dim
        if obs0.shape != (obs_dim,):
            raise ValueError(f"obs0 must have shape ({obs_dim},), got {tuple(obs0.shape)}")
        if generator is not None and generator.device.type != actions.device.type:
            raise ValueError(
                f"generator is on {generator.device}, the actions on {actions.device}: "
                "pass a generator created on the actions' device"
            )
        return obs0, actions

    def _model_dtype(self, fallback: torch.dtype) -> torch.dtype:
        """Dtype of the model's outputs in fp32 mode: its first floating parameter or buffer."""
        for t in (*self.model.parameters(), *self.model.buffers()):
            if t.is_floating_point():
                return t.dtype
        return fallback

    def _step(
        self,
        obs: Tensor,
        act: Tensor,
        noise: Tensor | None,
        done: Tensor,
        total: Tensor,
        members: Tensor | None,
        perm: Tensor | None,
        inv: Tensor | None,
        penalty: Tensor,
        zero: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """One model step for all rows: ``(obs, done, total) -> (next obs, done, total, step reward, went bad)``
        (``went bad``: the rows not done before whose transition was non-finite).

        ``noise`` ((M, B / M, target_dim), ts modes) and ``perm`` / ``inv`` (ts1) are drawn by the
        caller, so this function is pure (no randomness, no host synchronisation) and can be compiled.
        """
        dtype = total.dtype
        layout, sampling = self._propagation.layout, self._propagation.noise
        inp = self.model.inputs(obs, act)  # (b, in)
        if perm is not None:
            inp = inp.index_select(0, perm)
        with torch.autocast(device_type=obs.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            mean, logvar = layout.forward(self.model, inp, members, self._num_members(members))
        if self.precision == "bf16":  # back to float32 (the noise dtype) before any sampling
            out_dtype = zero.dtype if noise is None else noise.dtype
            mean, logvar = mean.to(out_dtype), logvar.to(out_dtype)
        target = layout.combine(sampling.target(mean, logvar, noise), inp.shape[0])
        if inv is not None:
            target = target.index_select(0, inv)
        nxt = self.model.next_obs(obs, target.to(dtype))
        reward = self.reward_fn(obs, act, nxt).to(dtype)
        # One row sum instead of isfinite + all over the state (measured ~10x cheaper): it is non-finite
        # exactly when a value or the reward is, or when finite values overflow float32 (a diverged row too).
        bad = ~torch.isfinite(nxt.sum(dim=-1) + reward)
        step_reward = torch.where(done, zero, torch.where(bad, penalty, reward))
        frozen = done | bad
        stop = frozen if self.terminated_fn is None else frozen | self.terminated_fn(obs, act, nxt).to(torch.bool)
        nxt = torch.where(frozen.unsqueeze(-1), obs, nxt)
        return nxt, stop, total + step_reward, step_reward, bad & ~done

    def _get_step(self) -> Callable[..., tuple[Tensor, Tensor, Tensor, Tensor, Tensor]]:
        """The step function: compiled (lazily, once per evaluator) when ``compile`` and it works, else eager."""
        if not self.compile or self._compile_failed:
            return self._step
        if self._compiled_step is None:
            self._compiled_step = torch.compile(self._step, backend=self.compile_backend)
        return self._compiled_step

    def _call_step(self, *args: Tensor | None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        step = self._get_step()
        if step is self._step:
            return step(*args)
        try:
            return step(*args)
        except Exception as err:  # compilation (or a compiled kernel) failed: warn once, eager from now on
            self._compile_failed = True
            self._compiled_step = None
            warnings.warn(
                f"TrajectoryEvaluator: torch.compile of the rollout step failed "
                f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}); "
                "using eager mode from now on",
                RuntimeWarning,
                stacklevel=3,
            )
            return self._step(*args)  # the step is pure: rerun it eagerly on the same inputs

    def horizon(self, actions: Tensor) -> int:
        """Rollout length of candidates ``actions``: H of a sequence, ``feedback.horizon`` for gains."""
        return self._candidates.horizon(actions)

    # ------------------------------------------------------------------ core
    def _run(
        self, obs0: Tensor, actions: Tensor, generator: torch.Generator | None, record: bool
    ) -> tuple[Tensor, Tensor | None, Tensor | None, int, Tensor]:
        """Roll out all rows. Returns (per-row return in natural order (R,), obs trace, reward trace, P_eff,
        whether the first transition of every row was non-finite (bool scalar on the device)).

        Natural order: row ``n * P_eff + p`` is particle ``p`` of candidate ``n``.
        Traces (when ``record``) are ``(R, H + 1, obs_dim)`` and ``(R, H)`` in natural order.
        """
        device, dtype = actions.device, actions.dtype
        n_cand = actions.shape[0]
        horizon = self.horizon(actions)
        members = self.members(device)
        m = self._num_members(members)
        layout, sampling = self._propagation.layout, self._propagation.noise
        p_eff = layout.particles(self.particles)
        rows = layout.arrange(n_cand, p_eff, m, device)
        b = rows.b
        per_row = self._candidates.per_row(actions, rows.cand)

        obs = obs0.expand(b, -1).clone()
        done = torch.zeros(b, dtype=torch.bool, device=device)
        total = torch.zeros(b, dtype=dtype, device=device)
        penalty = torch.tensor(self.nonfinite_reward, dtype=dtype, device=device)
        zero = torch.zeros((), dtype=dtype, device=device)
        obs_trace = [obs] if record else None
        rew_trace: list[Tensor] | None = [] if record else None
        noise_dtype = dtype if self.precision == "bf16" else self._model_dtype(dtype)
        noise = sampling.buffer((m, rows.per_member, self.model.target_dim), device, noise_dtype)
        diverged = None  # set at t = 0 (H >= 1, checked)

        with fused.cached_weights():  # CPU bf16 layers: weights prepared once per call (dynamics.fused)
            for t in range(horizon):
                perm, inv = layout.draw(rows, generator)
                sampling.draw(noise, generator)
                act = self._candidates.action(t, per_row, obs)
                obs, done, total, step_reward, went_bad = self._call_step(
                    obs, act, noise, done, total, members, perm, inv, penalty, zero
                )
                if t == 0:
                    diverged = went_bad  # rows with nothing finite at all
                if record:
                    obs_trace.append(obs)
                    rew_trace.append(step_reward)

        if self.terminal_value is not None:
            total = total + torch.where(done, torch.zeros_like(total), self.terminal_value(obs).to(total.dtype))
        if self.termination_penalty:
            total = total - done.to(total.dtype) * self.termination_penalty
        n_rows = n_cand * p_eff
        total = layout.natural(rows, total, n_rows)
        diverged = layout.natural(rows, diverged, n_rows)  # the real rows only, not the padding
        obs_all = layout.natural(rows, torch.stack(obs_trace, dim=1), n_rows) if record else None
        rew_all = layout.natural(rows, torch.stack(rew_trace, dim=1), n_rows) if record else None
        return total, obs_all, rew_all, p_eff, diverged.all()

    @torch.no_grad()
    def __call__(self, obs0: Tensor, actions: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Mean over particles of the summed horizon rewards (less ``risk_aversion`` times their standard
        deviation), shape (N,), for actions (N, H, act_dim).

        Finite for finite rewards of finite states (see the module docstring), except that every return is NaN
        when the first transition of every row is non-finite (a broken model: the planner then raises
        ``PlanningFailed``).
        """
        obs0, actions = self._check(obs0, actions, generator)
        total, _, _, p_eff, all_diverged = self._run(obs0, actions, generator, record=False)
        per_particle = total.view(actions.shape[0], p_eff)
        returns = per_particle.mean(dim=1)
        if self.risk_aversion and p_eff > 1:
            returns = returns - self.risk_aversion * per_particle.std(dim=1, correction=0)
        return torch.where(all_diverged, torch.full_like(returns, float("nan")), returns)

    @torch.no_grad()
    def rollout(self, obs0: Tensor, actions: Tensor, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """Particle trajectories for tests and diagnostics.

        Returns observations (N, P, H + 1, obs_dim) (index 0 is ``obs0``; frozen after a termination)
        and the rewards that count towards the return, (N, P, H) (zero after a termination,
        ``nonfinite_reward`` on a transition into a non-finite state), so that
        ``rewards.sum(-1).mean(-1)`` equals ``self(obs0, actions)`` for the same generator state without a
        ``terminal_value`` or ``risk_aversion`` (unless every row's first transition is non-finite: then the
        rewards keep the penalty and ``self`` returns NaN).
        For ``expectation`` the single rollout per candidate is repeated over the P particles.
        """
        obs0, actions = self._check(obs0, actions, generator)
        n, h = actions.shape[0], self.horizon(actions)
        _, obs_all, rew_all, p_eff, _ = self._run(obs0, actions, generator, record=True)
        obs_all = obs_all.view(n, p_eff, h + 1, -1).expand(n, self.particles, h + 1, obs_all.shape[-1])
        rew_all = rew_all.view(n, p_eff, h).expand(n, self.particles, h)
        return obs_all.contiguous(), rew_all.contiguous()
