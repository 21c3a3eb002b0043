"""Training of a dynamics model: bootstrap, holdout early stopping, per-member snapshots, elites.

The dynamics head decides what the network sees and predicts (``head.inputs``, ``head.targets``) and
how a batch is scored (``head.loss``, per member); the trainer itself is head-agnostic.

One epoch: every member walks through its own shuffled bootstrap resample of the training split;
each step gathers an (E, B, .) batch from the per-member indices and does one forward/backward for
all members. After each epoch every member's holdout error is computed (:meth:`ModelTrainer.evaluate`);
a member whose holdout error improved by more than ``improvement_threshold`` (relative) gets its
weights snapshotted. Training stops after ``patience`` epochs without any member improving; the
snapshot is restored and the ``num_elites`` members with the lowest holdout error become elites.

With ``iterations`` > 0 the schedule is the GEM paper's instead: exactly that many gradient steps, no early
stopping, the final weights kept (the holdout then only ranks the elites and reports the error). With
``bootstrap=False`` every member sees the same batches (the paper's ensembles, "trained in unison via total loss").

The holdout error is the same for every head: the standardised one-step error of the predicted next
observation, ``mean_d (pred_d - next_obs_d)^2 / var_d(next_obs - obs)`` over the observation entries the
model predicts (all but the layout's ``derived`` ones), ``var_d`` taken over the training data. It is
unitless (velocities do not drown positions) and about 1 for the "no change" predictor.

``compile=True`` (``model.compile``) runs every full minibatch as one compiled function
(:class:`~pets.learning.compiled.CompiledStep`: gradient by ``torch.func``, then the Adam update, in one
``torch.compile`` graph) on the epoch's batches gathered in one indexing op; the eager step above stays the reference
(and runs the epoch's last, partial batch). Same data, batches, seeds and validation criterion; the numerics differ by
float rounding (docs/performance.md, "Training at the fast preset").
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from torch import Tensor
from tqdm.auto import tqdm

from dynamics.model import DynamicsModel
from dynamics.networks import column_mean_std
from pets.learning.compiled import CompiledStep
from pets.learning.sampling import bootstrap_indices, split_holdout


def obs_change_scale(obs: Tensor, next_obs: Tensor, indices: Tensor) -> Tensor:
    """The units of the holdout error: the std of ``next_obs - obs`` per observation entry in ``indices``
    (a std < 1e-5 counts as 1)."""
    idx = indices.to(obs.device)
    return column_mean_std(next_obs.index_select(-1, idx) - obs.index_select(-1, idx))[1].to(obs)


class TrainingDiverged(RuntimeError):
    """Training made the model non-finite (a NaN/inf loss or parameter): it must not be used for planning."""


@dataclass
class TrainResult:
    """Outcome of one ``ModelTrainer.train`` call."""

    train_loss: float  # final epoch's mean training loss (head loss, mean over members and samples)
    val_loss: (
        float  # holdout error (see the module docstring) of the selected model, mean over elites (nan: no holdout)
    )
    epochs: int  # epochs actually run
    initial_val_loss: float = float("nan")  # the same for the weights this call started from (same members)
    #: ``(step, holdout error)`` every ``curve_every`` steps, from step 0 to the last (mean over all members)
    curve: tuple[tuple[int, float], ...] = ()


#: Full minibatches gathered per indexing op on the compiled path (bounds the gathered copy's memory).
GATHER_BATCHES = 64


def batch_gather(epoch_idx: Tensor, start: int, batch_size: int, tensors: tuple[Tensor, ...]) -> list[Tensor]:
    """The full (E, batch_size) minibatches of ``epoch_idx`` (E, n) from column ``start`` on, up to
    :data:`GATHER_BATCHES` of them, gathered from each (n_data, d) tensor in one indexing op: a list of
    (batches, E, batch_size, d) tensors whose ``[k]`` is minibatch k, contiguous."""
    e, n = epoch_idx.shape
    count = min(GATHER_BATCHES, (n - start) // batch_size)
    idx = epoch_idx[:, start : start + count * batch_size].reshape(e, count, batch_size).transpose(0, 1).contiguous()
    return [t[idx] for t in tensors]


class ModelTrainer:
    """Adam training of a :class:`dynamics.model.DynamicsModel`.

    Loss per step: ``model.member_loss(...).sum()`` (members summed) plus the model's regularisers (weight decay,
    and ``logvar_bound_coef`` times the log-variance bound penalty where the bounds are learnt).
    Every ``train`` call refits the model's input and target normalisers on all its data.
    The optimiser persists across ``train`` calls (one call per PETS trial).
    ``compile``: full minibatches run as one compiled step (:class:`CompiledStep`, built once per trainer with
    ``torch.compile(backend=compile_backend)``; a failure to compile warns once and trains eagerly from then on).
    """

    def __init__(
        self,
        model: DynamicsModel,
        *,
        lr: float = 1e-3,
        batch_size: int = 256,
        max_epochs: int = 50,
        patience: int = 5,
        holdout_ratio: float = 0.1,
        max_holdout: int = 5000,
        num_elites: int | None = None,
        logvar_bound_coef: float = 0.01,
        grad_clip: float | None = None,
        improvement_threshold: float = 0.01,
        eval_batch_size: int = 8192,
        iterations: int = 0,
        bootstrap: bool = True,
        precision: str = "fp32",
        compile: bool = False,
        compile_backend: str | Callable = "inductor",
        curve_every: int = 0,
    ) -> None:
        if not (math.isfinite(lr) and lr >= 0):
            raise ValueError(f"lr must be a finite number >= 0, got {lr}")
        for name, value, low in (
            ("batch_size", batch_size, 1),
            ("max_epochs", max_epochs, 0),
            ("patience", patience, 1),
            ("max_holdout", max_holdout, 0),
            ("eval_batch_size", eval_batch_size, 1),
            ("iterations", iterations, 0),
            ("curve_every", curve_every, 0),
        ):
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
        if precision not in ("fp32", "bf16"):
            raise ValueError(f"precision must be fp32 or bf16, got {precision!r}")
        if not isinstance(compile, bool):
            raise ValueError(f"compile must be a bool, got {compile!r}")
        if not 0.0 <= holdout_ratio < 1.0:
            raise ValueError(f"holdout_ratio must be in [0, 1), got {holdout_ratio}")
        if num_elites is None:
            num_elites = model.network.num_elites
        if not isinstance(num_elites, int) or not 1 <= num_elites <= model.ensemble_size:
            raise ValueError(f"num_elites must be an int in [1, {model.ensemble_size}], got {num_elites!r}")
        if grad_clip is not None and not grad_clip > 0:
            raise ValueError(f"grad_clip must be None or > 0, got {grad_clip}")
        if not improvement_threshold >= 0:
            raise ValueError(f"improvement_threshold must be >= 0, got {improvement_threshold}")

        self.model = model
        self.lr = lr
        self.batch_size = batch_size
        self.max_epochs = max_epochs
        self.patience = patience
        self.holdout_ratio = holdout_ratio
        self.max_holdout = max_holdout
        self.num_elites = num_elites
        self.logvar_bound_coef = logvar_bound_coef
        self.grad_clip = grad_clip
        self.improvement_threshold = improvement_threshold
        self.eval_batch_size = eval_batch_size
        self.iterations = iterations
        self.curve_every = curve_every
        self.bootstrap = bool(bootstrap)
        #: ``bf16``: training steps under bfloat16 autocast (fp32 weights, optimiser, loss and holdout error).
        self.precision = precision
        #: ``True``: full minibatches run as one compiled step (:class:`CompiledStep`); the eager step is the reference.
        self.compile = compile
        self.compile_backend = compile_backend
        self._compiled: CompiledStep | None = None
        self._compile_failed = False
        self.optimizer = torch.optim.Adam(model.parameters(), lr=lr)
        self._predicted = torch.tensor(model.head.layout.predicted_indices, dtype=torch.long)
        #: Per-entry std of ``next_obs - obs`` (predicted entries) that :meth:`evaluate` divides by; set by ``train``.
        self.error_scale: Tensor | None = None

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """Optimiser state (the ensemble has its own ``state_dict``)."""
        return {"optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, d: dict) -> None:
        """Restore the optimiser state saved by :meth:`state_dict`."""
        if "optimizer" not in d:
            raise ValueError(f"trainer state must have an 'optimizer' entry, got keys {sorted(d)}")
        # Deep copy: torch's Adam would otherwise share the moment tensors with the source optimiser.
        self.optimizer.load_state_dict(copy.deepcopy(d["optimizer"]))

    # ------------------------------------------------------------------ evaluation
    def fit_error_scale(self, obs: Tensor, next_obs: Tensor) -> None:
        """Set :attr:`error_scale` from transitions: the std of ``next_obs - obs`` per predicted entry (< 1e-5 -> 1)."""
        self.error_scale = obs_change_scale(obs, next_obs, self._predicted)

    @torch.no_grad()
    def evaluate(self, x: Tensor, obs: Tensor, next_obs: Tensor) -> Tensor:
        """Per-member holdout error (E,) of the mean prediction: ``mean_d (pred_d - next_obs_d)^2 / error_scale_d^2``
        over the predicted observation entries, ``pred = model.next_obs(obs, mean)``. ``x = model.inputs(obs, act)``;
        all (N, .). :meth:`fit_error_scale` first (``train`` does)."""
        if self.error_scale is None:
            raise ValueError("evaluate needs error_scale: call fit_error_scale(obs, next_obs) (or train) first")
        idx = self._predicted.to(obs.device)
        scale = self.error_scale.to(obs)
        total = x.new_zeros(self.model.ensemble_size, dtype=torch.float64)
        for start in range(0, x.shape[0], self.eval_batch_size):
            chunk = slice(start, start + self.eval_batch_size)
            mean, _ = self.model(x[chunk])
            pred = self.model.next_obs(obs[chunk], mean)  # (E, B, obs_dim)
            err = ((pred - next_obs[chunk]).index_select(-1, idx) / scale).pow(2)
            total += err.sum(dim=(1, 2)).double()
        return total / (x.shape[0] * idx.numel())

    # ------------------------------------------------------------------ training
    def _compiled_step(self, bf16: bool) -> CompiledStep | None:
        """The compiled step (built once per trainer) when ``compile`` is on and has not failed, else None."""
        if not self.compile or self._compile_failed or self.grad_clip is not None:
            return None
        if self._compiled is None or self._compiled.loss.bf16 != bf16 or self._compiled.optimizer is not self.optimizer:
            try:
                self._compiled = CompiledStep(
                    self.model, self.optimizer, self.logvar_bound_coef, bf16, self.compile_backend
                )
            except Exception as err:  # an unknown backend, an unsupported optimiser setting
                self._compile_failed = True
                warnings.warn(
                    f"ModelTrainer: no compiled training step ({err}); using the eager step",
                    RuntimeWarning,
                    stacklevel=3,
                )
                return None
        return self._compiled

    def _run_compiled(self, step: CompiledStep, *batch: Tensor) -> Tensor | None:
        """``step(*batch)``; None (after a warning, and eager from then on) if compiling it failed."""
        try:
            return step(*batch)
        except Exception as err:  # e.g. no C++ compiler for inductor: the eager step reruns this batch
            self._compile_failed = True
            warnings.warn(
                f"ModelTrainer: torch.compile of the training step failed ({type(err).__name__}: "
                f"{str(err).splitlines()[0] if str(err) else ''}); using the eager step from now on",
                RuntimeWarning,
                stacklevel=3,
            )
            return None

    def _check_data(self, obs: Tensor, act: Tensor, next_obs: Tensor) -> None:
        if obs.dim() != 2 or next_obs.shape != obs.shape or act.dim() != 2 or act.shape[0] != obs.shape[0]:
            raise ValueError(
                f"train expects obs (N, obs_dim), act (N, act_dim), next_obs (N, obs_dim); got obs "
                f"{tuple(obs.shape)}, act {tuple(act.shape)}, next_obs {tuple(next_obs.shape)}"
            )
        if obs.shape[0] < 1:
            raise ValueError("train got an empty data set (N = 0)")
        for name, t in (("obs", obs), ("act", act), ("next_obs", next_obs)):
            if not torch.isfinite(t).all():
                raise ValueError(f"train got non-finite values (nan/inf) in {name}")

    def _check_finite(self, train_loss: float, epoch: int) -> None:
        """TrainingDiverged unless the epoch's loss and every parameter (log-variance bounds included) are finite."""
        bad = [name for name, p in self.model.named_parameters() if not bool(torch.isfinite(p).all())]
        if math.isfinite(train_loss) and not bad:
            return
        what = f"parameters {', '.join(bad[:3])}{' ...' if len(bad) > 3 else ''}" if bad else "the loss"
        raise TrainingDiverged(
            f"model training diverged in epoch {epoch}: {what} became non-finite (train loss {train_loss:.4g}); "
            f"lower model.lr (now {self.lr:g}) or check the data for extreme values"
        )

    def train(
        self,
        obs: Tensor,
        act: Tensor,
        next_obs: Tensor,
        generator: torch.Generator,
        progress: bool = False,
        validation: tuple[Tensor, Tensor, Tensor] | None = None,
    ) -> TrainResult:
        """Fit the model on transitions (obs, act, next_obs), each (N, .); all randomness from ``generator``.

        Refits the normalisers on all the data, splits off a holdout (or uses ``validation``, a separate
        ``(obs, act, next_obs)`` set, as it), trains with per-member bootstraps and early stopping (or the fixed
        ``iterations``), restores the best per-member weights and sets the model's elites.
        """
        self._check_data(obs, act, next_obs)
        if validation is not None:
            self._check_data(*validation)
        model = self.model
        ref = model.member_parameters()[0]  # device and dtype of the model
        train, holdout = self._split(obs, act, next_obs, generator, validation)
        x_tr = train[0]
        has_holdout = holdout[0].shape[0] > 0
        n_tr = x_tr.shape[0]
        if self.bootstrap:
            boot = bootstrap_indices(n_tr, model.ensemble_size, generator).to(ref.device)  # (E, n_tr)
        else:  # every member on the same data, in the same order
            boot = torch.arange(n_tr, device=ref.device).expand(model.ensemble_size, n_tr)
        fixed = self.iterations > 0
        bf16 = self.precision == "bf16"
        max_epochs = math.ceil(self.iterations / math.ceil(n_tr / self.batch_size)) if fixed else self.max_epochs

        params = model.member_parameters()
        best = self.evaluate(*holdout) if has_holdout else None
        initial = best
        snapshot = [p.detach().clone() for p in params] if has_holdout and not fixed else None  # fixed: final weights
        since_improved = 0
        epochs = steps = 0
        train_loss = float("nan")
        curve = [(0, float(initial.mean()))] if self.curve_every and has_holdout else None
        bar = tqdm(range(max_epochs), disable=not progress, desc="model", leave=False)
        for _ in bar:
            # Per-member shuffle of the member's bootstrap resample (one argsort for all members).
            rows = model.ensemble_size if self.bootstrap else 1
            order = torch.argsort(torch.rand(rows, n_tr, generator=generator, device=generator.device), dim=1)
            epoch_idx = torch.gather(boot, 1, order.to(ref.device).expand(model.ensemble_size, n_tr))
            train_loss, steps = self._epoch(epoch_idx, train, bf16, fixed, steps, curve, holdout)
            epochs += 1
            self._check_finite(train_loss, epochs)

            if not has_holdout or fixed:
                bar.set_postfix(loss=f"{train_loss:.4g}")
                continue
            score = self.evaluate(*holdout)
            improved = (best - score) / best.abs().clamp_min(1e-12) > self.improvement_threshold  # (E,)
            best = torch.where(improved, score, best)
            mask = improved.to(ref.device).view(-1, 1, 1)
            for snap, p in zip(snapshot, params):
                snap.copy_(torch.where(mask, p.detach(), snap))
            since_improved = 0 if bool(improved.any()) else since_improved + 1
            bar.set_postfix(loss=f"{train_loss:.4g}", val=f"{float(best.mean()):.4g}")
            if since_improved >= self.patience:
                break
        bar.close()
        if curve is not None and curve[-1][0] != steps:  # the last step, where the curve's stride missed it
            curve.append((steps, float(self.evaluate(*holdout).mean())))
        result = self._finish(train, holdout, fixed, snapshot, best, initial, train_loss, epochs)
        return result if curve is None else replace(result, curve=tuple(curve))

    def _split(
        self,
        obs: Tensor,
        act: Tensor,
        next_obs: Tensor,
        generator: torch.Generator,
        validation: tuple[Tensor, Tensor, Tensor] | None,
    ) -> tuple[tuple[Tensor, Tensor, Tensor, Tensor], tuple[Tensor, Tensor, Tensor]]:
        """Refit the normalisers and the error scale on all the data, then split it: ``((x, y, obs, next_obs)`` to
        train on, ``(x, obs, next_obs)`` held out``)``: a random holdout, or ``validation`` when given."""
        model = self.model
        ref = model.member_parameters()[0]  # device and dtype of the model
        obs, act, next_obs = (t.to(device=ref.device, dtype=ref.dtype) for t in (obs, act, next_obs))
        x, y = model.inputs(obs, act), model.targets(obs, next_obs)
        model.fit_normalisers(x, y)
        self.fit_error_scale(obs, next_obs)

        if validation is None:
            train_idx, hold_idx = split_holdout(x.shape[0], self.holdout_ratio, self.max_holdout, generator)
            train_idx, hold_idx = train_idx.to(ref.device), hold_idx.to(ref.device)
            x_tr, y_tr, o_tr, no_tr = (t.index_select(0, train_idx) for t in (x, y, obs, next_obs))
            x_ho, o_ho, no_ho = (t.index_select(0, hold_idx) for t in (x, obs, next_obs))
        else:
            x_tr, y_tr, o_tr, no_tr = x, y, obs, next_obs
            o_ho, a_ho, no_ho = (t.to(device=ref.device, dtype=ref.dtype) for t in validation)
            x_ho = model.inputs(o_ho, a_ho)
        return (x_tr, y_tr, o_tr, no_tr), (x_ho, o_ho, no_ho)

    def _epoch(
        self,
        epoch_idx: Tensor,
        train: tuple[Tensor, Tensor, Tensor, Tensor],
        bf16: bool,
        fixed: bool,
        steps: int,
        curve: list[tuple[int, float]] | None = None,
        holdout: tuple[Tensor, Tensor, Tensor] | None = None,
    ) -> tuple[float, int]:
        """One pass over the (E, n) per-member indices ``epoch_idx`` into ``train`` in minibatches (with ``fixed``,
        up to ``iterations`` steps in all): the mean training loss and the steps done so far. ``curve``: appends
        the holdout error every ``curve_every`` steps."""
        model = self.model
        x_tr, y_tr, o_tr, no_tr = train
        n_tr = x_tr.shape[0]
        loss_sum, seen = x_tr.new_zeros(()), 0
        gathered: list[Tensor] = []
        for start in range(0, n_tr, self.batch_size):
            if fixed and steps == self.iterations:
                break
            idx = epoch_idx[:, start : start + self.batch_size]  # (E, B)
            step = self._compiled_step(bf16) if idx.shape[1] == self.batch_size else None
            if step is not None:  # full batches: gathered GATHER_BATCHES at a time, one indexing op per tensor
                k = (start // self.batch_size) % GATHER_BATCHES
                if k == 0:
                    gathered = batch_gather(epoch_idx, start, self.batch_size, train)
                mean_loss = self._run_compiled(step, *(t[k] for t in gathered))
            else:
                mean_loss = None
            if mean_loss is None:  # the reference step
                member_loss = model.member_loss(x_tr[idx], y_tr[idx], o_tr[idx], no_tr[idx], bf16=bf16)  # (E,)
                loss = model.add_regularisers(member_loss.sum(), self.logvar_bound_coef)
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                if self.grad_clip is not None:
                    torch.nn.utils.clip_grad_norm_(model.parameters(), self.grad_clip)
                self.optimizer.step()
                mean_loss = member_loss.detach().mean()
            loss_sum = loss_sum + mean_loss * idx.shape[1]
            seen += idx.shape[1]
            steps += 1
            if curve is not None and steps % self.curve_every == 0:
                curve.append((steps, float(self.evaluate(*holdout).mean())))
        return float(loss_sum) / seen, steps

    def _finish(
        self,
        train: tuple[Tensor, Tensor, Tensor, Tensor],
        holdout: tuple[Tensor, Tensor, Tensor],
        fixed: bool,
        snapshot: list[Tensor] | None,
        best: Tensor | None,
        initial: Tensor | None,
        train_loss: float,
        epochs: int,
    ) -> TrainResult:
        """Keep the final weights (``fixed``) or restore the snapshot, set the elites, and report."""
        has_holdout = holdout[0].shape[0] > 0
        if has_holdout and fixed:  # the final weights are the model
            scores = self.evaluate(*holdout)
        elif has_holdout:
            with torch.no_grad():
                for snap, p in zip(snapshot, self.model.member_parameters()):
                    p.copy_(snap)
            scores = best
        else:  # no holdout: rank members on their training-split error
            x_tr, _, o_tr, no_tr = train
            scores = self.evaluate(x_tr, o_tr, no_tr)
        elites = torch.sort(torch.argsort(scores, stable=True)[: self.num_elites]).values
        self.model.set_elites(elites)
        if not has_holdout:
            return TrainResult(train_loss=train_loss, val_loss=float("nan"), epochs=epochs)
        return TrainResult(
            train_loss=train_loss,
            val_loss=float(scores[elites].mean()),
            epochs=epochs,
            initial_val_loss=float(initial[elites].mean()),
        )
