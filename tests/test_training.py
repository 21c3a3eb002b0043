"""Tests of the ensemble trainer (pets/learning/trainer.py)."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from dynamics.heads import DeltaHead, DynamicsHead
from dynamics.model import DynamicsModel
from dynamics.networks import GaussianEnsemble
from envs.layout import ObsLayout
from pets.learning.sampling import bootstrap_indices, split_holdout
from pets.learning.trainer import ModelTrainer, TrainResult

LAYOUT_1D = ObsLayout(obs_dim=1, groups=(), velocities=(0,))


pytestmark = pytest.mark.usefixtures("single_thread")


class IdentityHead(DynamicsHead):
    """Tiny head: input = obs, target = next_obs; optionally records what each member is trained on."""

    name = "identity"

    def __init__(self, record: bool = False, target_shift: float = 0.0) -> None:
        super().__init__(LAYOUT_1D, 0)
        self.input_dim = 1
        self.target_dim = 1
        self.record = record
        self.target_shift = target_shift
        self.seen: list[Tensor] = []

    def inputs(self, obs: Tensor, act: Tensor) -> Tensor:
        return obs

    def targets(self, obs: Tensor, next_obs: Tensor) -> Tensor:
        return next_obs

    def next_obs(self, obs: Tensor, target: Tensor) -> Tensor:
        return target

    def loss(
        self, mean: Tensor, logvar: Tensor, target: Tensor, obs: Tensor, next_obs: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        if self.record:
            self.seen.append(obs[..., 0].detach().clone())  # (E, B)
        if self.target_shift:  # adversarial: pull the mean away from the true target
            return (mean - target - self.target_shift).pow(2).flatten(1).mean(1)
        return super().loss(mean, logvar, target, obs, next_obs)


def small_ensemble(seed: int = 0, ensemble_size: int = 5, hidden: int = 32, layers: int = 2, **kw) -> GaussianEnsemble:
    torch.manual_seed(seed)
    return GaussianEnsemble(1, 1, ensemble_size=ensemble_size, hidden_size=hidden, num_layers=layers, **kw)


def sine_data(n: int, seed: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """x ~ U(-3, 3); y = sin(x) + sigma(x) * eps with sigma(x) = 0.05 + 0.25 * (x + 3) / 6."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 1, generator=g) * 6 - 3
    sigma = 0.05 + 0.25 * (x + 3) / 6
    y = torch.sin(x) + sigma * torch.randn(n, 1, generator=g)
    return x, torch.zeros(n, 0), y, sigma


def test_bootstrap_indices_with_replacement_and_distinct_per_member() -> None:
    g = torch.Generator().manual_seed(3)
    idx = bootstrap_indices(2000, 7, g)
    assert idx.shape == (7, 2000) and idx.dtype == torch.long
    assert idx.min() >= 0 and idx.max() < 2000
    unique_frac = torch.tensor([row.unique().numel() / 2000 for row in idx])
    # With replacement: about 1 - 1/e = 63.2% distinct indices per resample.
    assert torch.all((unique_frac > 0.60) & (unique_frac < 0.66))
    for a in range(7):
        for b in range(a + 1, 7):
            assert not torch.equal(idx[a], idx[b])
    assert torch.equal(idx, bootstrap_indices(2000, 7, torch.Generator().manual_seed(3)))


def test_split_holdout_sizes() -> None:
    g = torch.Generator().manual_seed(0)
    tr, ho = split_holdout(1000, 0.1, 5000, g)
    assert ho.numel() == 100 and tr.numel() == 900
    assert torch.equal(torch.sort(torch.cat([tr, ho])).values, torch.arange(1000))
    assert split_holdout(100_000, 0.1, 5000, g)[1].numel() == 5000  # capped
    assert split_holdout(9, 0.1, 5000, g)[1].numel() == 0  # too few samples: no holdout
    assert split_holdout(1, 0.9, 5000, g)[1].numel() == 0  # would leave no training sample


def test_trainer_feeds_each_member_its_own_bootstrap_of_the_train_split() -> None:
    n = 200
    obs = torch.arange(n, dtype=torch.float32)[:, None]
    head = IdentityHead(record=True)
    ens = small_ensemble(ensemble_size=4)
    trainer = ModelTrainer(DynamicsModel(head, ens), batch_size=32, max_epochs=2, patience=5, holdout_ratio=0.1)
    trainer.train(obs, torch.zeros(n, 0), obs.clone(), torch.Generator().manual_seed(1))
    batches_per_epoch = math.ceil(180 / 32)
    assert len(head.seen) == 2 * batches_per_epoch
    epoch1 = torch.cat(head.seen[:batches_per_epoch], dim=1).long()  # (E, 180)
    epoch2 = torch.cat(head.seen[batches_per_epoch:], dim=1).long()
    assert epoch1.shape == (4, 180)
    train_ids = torch.unique(epoch1)
    assert train_ids.numel() <= 180  # the 20 holdout samples are never trained on
    counts = torch.stack([torch.bincount(row, minlength=n) for row in epoch1])  # (E, n)
    assert torch.all(counts.max(dim=1).values >= 2)  # drawn with replacement
    assert all(not torch.equal(counts[a], counts[b]) for a in range(4) for b in range(a + 1, 4))
    # The same resample every epoch, in a new order.
    counts2 = torch.stack([torch.bincount(row, minlength=n) for row in epoch2])
    assert torch.equal(counts, counts2)
    assert not torch.equal(epoch1, epoch2)


def _train_once(seed: int, gen_seed: int) -> tuple[TrainResult, dict]:
    x, act, y, _ = sine_data(300, seed=0)
    ens = small_ensemble(seed=seed, num_elites=3)
    trainer = ModelTrainer(DynamicsModel(DeltaHead(LAYOUT_1D, 0), ens), batch_size=32, max_epochs=4, patience=2)
    result = trainer.train(x, act, x + y, torch.Generator().manual_seed(gen_seed))
    return result, ens.state_dict()


def test_reproducible_with_same_generator_seed() -> None:
    r1, s1 = _train_once(0, 7)
    r2, s2 = _train_once(0, 7)
    assert r1 == r2
    assert s1.keys() == s2.keys()
    for k in s1:
        assert torch.equal(s1[k], s2[k]), k
    r3, s3 = _train_once(0, 8)
    assert r3.train_loss != r1.train_loss
    assert not torch.equal(s3["weights.0"], s1["weights.0"])


def test_early_stopping_with_no_progress_stops_after_patience() -> None:
    x, act, y, _ = sine_data(200, seed=1)
    ens = small_ensemble()
    trainer = ModelTrainer(
        DynamicsModel(DeltaHead(LAYOUT_1D, 0), ens), lr=0.0, batch_size=64, max_epochs=50, patience=3
    )
    result = trainer.train(x, act, x + y, torch.Generator().manual_seed(0))
    assert result.epochs == 3


def test_early_stopping_restores_best_weights_when_validation_gets_worse() -> None:
    # The adversarial head trains every member towards target + 5, so the holdout error only grows:
    # training must stop after `patience` epochs and hand back the untouched initial weights.
    n = 300
    obs = torch.rand(n, 1) * 2 - 1
    ens = small_ensemble()
    initial = [p.detach().clone() for p in ens.member_parameters()]
    trainer = ModelTrainer(
        DynamicsModel(IdentityHead(target_shift=5.0), ens), lr=1e-2, batch_size=32, max_epochs=50, patience=4
    )
    result = trainer.train(obs, torch.zeros(n, 0), torch.zeros(n, 1), torch.Generator().manual_seed(0))
    assert result.epochs == 4
    for before, after in zip(initial, ens.member_parameters()):
        assert torch.equal(before, after)
    with torch.no_grad():
        mean, _ = ens(obs)
    assert mean.abs().max() < 2.0  # nowhere near the adversarial target 5


def test_elites_are_lowest_holdout_error_members() -> None:
    # Constant predictors (zero output weights, mean bias b_k) against target 0: holdout error_k = b_k^2 / var,
    # var the variance of next_obs - obs (= -obs) over the data (the target normaliser is the identity here:
    # the targets are all 0, their std is taken as 1).
    n = 400
    obs = torch.randn(n, 1)
    ens = small_ensemble(ensemble_size=7)
    offsets = torch.tensor([3.0, 0.1, 2.0, 0.0, 5.0, -0.2, 1.0])
    with torch.no_grad():
        ens.weights[-1].zero_()
        ens.biases[-1][:, 0, 0] = offsets
    trainer = ModelTrainer(DynamicsModel(IdentityHead(), ens), lr=0.0, max_epochs=2, patience=1, num_elites=3)
    result = trainer.train(obs, torch.zeros(n, 0), torch.zeros(n, 1), torch.Generator().manual_seed(0))
    assert ens.elites.tolist() == [1, 3, 5]
    assert float(trainer.error_scale[0]) == pytest.approx(float(obs.std(correction=0)), rel=1e-5)
    assert result.val_loss == pytest.approx((0.1**2 + 0.0 + 0.2**2) / 3 / float(obs.var(correction=0)), rel=1e-4)
    # Without a holdout the elites come from the training error: the same ranking here.
    ens.set_elites(torch.arange(7))
    trainer2 = ModelTrainer(
        DynamicsModel(IdentityHead(), ens), lr=0.0, max_epochs=2, patience=1, num_elites=2, holdout_ratio=0.0
    )
    result2 = trainer2.train(obs, torch.zeros(n, 0), torch.zeros(n, 1), torch.Generator().manual_seed(0))
    assert ens.elites.tolist() == [1, 3]
    assert math.isnan(result2.val_loss) and result2.epochs == 2


def test_fits_heteroscedastic_sine_with_delta_head() -> None:
    x, act, y, _ = sine_data(1200, seed=2)
    obs, next_obs = x, x + y  # delta target = next_obs - obs = y
    ens = small_ensemble(seed=1, ensemble_size=4, hidden=64, layers=3, num_elites=3)
    trainer = ModelTrainer(DynamicsModel(DeltaHead(LAYOUT_1D, 0), ens), batch_size=64, max_epochs=60, patience=8)
    result = trainer.train(obs, act, next_obs, torch.Generator().manual_seed(0), progress=True)
    assert result.epochs > trainer.patience  # it did learn for a while
    assert ens.elites.numel() == 3
    grid = torch.linspace(-2.8, 2.8, 57)[:, None]
    with torch.no_grad():
        mean, logvar = ens(grid, ens.elites)
    mean = mean.mean(0)[:, 0]
    std = logvar.mean(0)[:, 0].mul(0.5).exp()
    true_std = 0.05 + 0.25 * (grid[:, 0] + 3) / 6
    assert (mean - torch.sin(grid[:, 0])).abs().max() < 0.15
    assert (mean - torch.sin(grid[:, 0])).abs().mean() < 0.05
    ratio = std / true_std
    assert ratio.min() > 0.5 and ratio.max() < 2.0  # the learned noise level tracks sigma(x) roughly
    assert std[-5:].mean() > 2.5 * std[:5].mean()  # and grows with x like the true noise (x4 end to end)
    # The holdout error is the squared error of the mean divided by var(y): about the average noise variance
    # (~0.033) plus a small fit error, over var(y) (~0.5).
    var = float(y.var(correction=0))
    assert 0.015 / var < result.val_loss < 0.06 / var
    assert result.train_loss < -0.8  # NLL/2 without the constant: about mean(log sigma) + 0.5 = -1.3 at best


def test_optimizer_checkpoint_roundtrip_continues_identically() -> None:
    x, act, y, _ = sine_data(300, seed=3)
    head = DeltaHead(LAYOUT_1D, 0)
    ens_a = small_ensemble(seed=4)
    trainer_a = ModelTrainer(DynamicsModel(head, ens_a), batch_size=32, max_epochs=2, patience=5)
    trainer_a.train(x, act, x + y, torch.Generator().manual_seed(0))
    ens_b = small_ensemble(seed=99)
    trainer_b = ModelTrainer(DynamicsModel(head, ens_b), batch_size=32, max_epochs=2, patience=5)
    ens_b.load_state_dict(ens_a.state_dict())
    trainer_b.load_state_dict(trainer_a.state_dict())
    ra = trainer_a.train(x, act, x + y, torch.Generator().manual_seed(1))
    rb = trainer_b.train(x, act, x + y, torch.Generator().manual_seed(1))
    assert ra == rb
    for (k, pa), pb in zip(ens_a.state_dict().items(), ens_b.state_dict().values()):
        assert torch.equal(pa, pb), k
    with pytest.raises(ValueError, match="optimizer"):
        trainer_b.load_state_dict({})


def test_bad_arguments_raise() -> None:
    ens = small_ensemble()
    head = DeltaHead(ObsLayout(obs_dim=2, groups=(), velocities=(0, 1)), 1)  # input_dim 3, target_dim 2
    with pytest.raises(ValueError, match="input_dim"):
        DynamicsModel(head, ens)
    ok_head = DeltaHead(LAYOUT_1D, 0)
    with pytest.raises(ValueError, match="num_elites"):
        ModelTrainer(DynamicsModel(ok_head, ens), num_elites=6)
    with pytest.raises(ValueError, match="holdout_ratio"):
        ModelTrainer(DynamicsModel(ok_head, ens), holdout_ratio=1.0)
    with pytest.raises(ValueError, match="patience"):
        ModelTrainer(DynamicsModel(ok_head, ens), patience=0)
    trainer = ModelTrainer(DynamicsModel(ok_head, ens))
    g = torch.Generator().manual_seed(0)
    with pytest.raises(ValueError, match="obs"):
        trainer.train(torch.zeros(10, 1), torch.zeros(9, 0), torch.zeros(10, 1), g)
    with pytest.raises(ValueError, match="non-finite"):
        trainer.train(torch.full((10, 1), float("nan")), torch.zeros(10, 0), torch.zeros(10, 1), g)


def test_a_diverging_optimiser_raises_instead_of_returning_a_nan_model() -> None:
    from pets.learning.trainer import TrainingDiverged

    x, act, y, _ = sine_data(200, seed=1)
    for holdout_ratio in (0.1, 0.0):
        trainer = ModelTrainer(
            DynamicsModel(DeltaHead(LAYOUT_1D, 0), small_ensemble()), lr=1e6, max_epochs=20, holdout_ratio=holdout_ratio
        )
        with pytest.raises(
            TrainingDiverged, match=r"diverged in epoch \d+: .*non-finite.*lower model.lr \(now 1e\+06\)"
        ):
            trainer.train(x, act, x + y, torch.Generator().manual_seed(0))


def test_fixed_iterations_in_unison_take_exactly_n_steps_on_the_same_batches() -> None:
    """The GEM paper's schedule: N gradient steps, no early stopping, every member on the same batches."""
    n = 100
    obs = torch.arange(n, dtype=torch.float32)[:, None]
    head = IdentityHead(record=True)
    ens = small_ensemble(ensemble_size=3)
    val = (obs[:10] + 0.5, torch.zeros(10, 0), obs[:10] + 0.5)
    trainer = ModelTrainer(
        DynamicsModel(head, ens), batch_size=10, max_epochs=1, patience=1, iterations=23, bootstrap=False
    )
    result = trainer.train(obs, torch.zeros(n, 0), obs.clone(), torch.Generator().manual_seed(0), validation=val)
    assert len(head.seen) == 23  # max_epochs and patience do not apply
    assert trainer.optimizer.state_dict()["state"][0]["step"] == 23
    for batch in head.seen:
        assert all(torch.equal(batch[0], batch[m]) for m in range(1, 3))  # members in unison
    first_epoch = torch.cat(head.seen[:10], dim=1)[0].long()
    assert torch.equal(torch.sort(first_epoch).values, torch.arange(n))  # all the training data, each once
    assert result.epochs == 3 and math.isfinite(result.val_loss)
    # the separate validation set is what scores the members (and the result)
    assert result.val_loss == pytest.approx(float(trainer.evaluate(val[0], val[0], val[2]).mean()), rel=1e-6)


def test_members_with_equal_weights_stay_equal_when_trained_in_unison() -> None:
    """Unison: equal members stay equal (up to float rounding of the batched matmuls); bootstraps split them."""
    x, act, y, _ = sine_data(200, seed=1)

    def spread(bootstrap: bool) -> float:
        ens = small_ensemble(ensemble_size=3)
        with torch.no_grad():
            for p in ens.member_parameters():
                p.copy_(p[:1].expand_as(p))
        model = DynamicsModel(DeltaHead(LAYOUT_1D, 0), ens)
        trainer = ModelTrainer(model, batch_size=16, iterations=30, bootstrap=bootstrap)
        trainer.train(x, act, x + y, torch.Generator().manual_seed(0))
        return max(float((p - p[:1]).detach().abs().max()) for p in ens.member_parameters())

    assert spread(False) < 1e-5
    assert spread(True) > 1e-3


def test_a_checkpoint_of_the_old_module_path_still_loads(tmp_path, monkeypatch):
    """Checkpoints pickle ``last_train`` (a TrainResult) by its module path, ``pets.trainer`` before the library
    moved into subpackages (issue 33): such a checkpoint loads as the TrainResult of ``pets.learning.trainer``."""
    import sys
    import types

    from pets.runs import rundir

    result = TrainResult(train_loss=1.0, val_loss=2.0, epochs=3, initial_val_loss=4.0)
    old = types.ModuleType("pets.trainer")
    old.TrainResult = TrainResult
    monkeypatch.setitem(sys.modules, "pets.trainer", old)
    monkeypatch.setattr(TrainResult, "__module__", "pets.trainer")
    rundir.save_checkpoint(tmp_path, {"last_train": result})
    assert b"pets.trainer" in (tmp_path / rundir.CHECKPOINT_FILE).read_bytes()
    monkeypatch.undo()
    assert "pets.trainer" not in sys.modules and TrainResult.__module__ == "pets.learning.trainer"
    state = rundir.load_checkpoint(tmp_path)
    assert state["last_train"] == result


def test_the_learning_curve_under_early_stopping_ends_at_the_last_step_not_at_the_restored_weights() -> None:
    """curve_every=7 with holdout early stopping: the curve starts at the initial holdout error (mean over all
    members), has a point every 7 steps and one at the last step, evaluated before the best weights are restored
    (so it can end above the result's val_loss); the training itself is bit for bit the one without a curve."""
    x, act, y, _ = sine_data(400, seed=1)
    results, states = [], []
    for curve_every in (0, 7):
        model = DynamicsModel(IdentityHead(), small_ensemble(seed=2))
        trainer = ModelTrainer(model, batch_size=32, max_epochs=6, patience=50, curve_every=curve_every)
        results.append(trainer.train(x, act, y, torch.Generator().manual_seed(0)))
        states.append(model.state_dict())
    plain, curved = results
    assert plain.curve == () and (plain.train_loss, plain.val_loss) == (curved.train_loss, curved.val_loss)
    assert all(torch.equal(states[0][k], states[1][k]) for k in states[0])
    steps = [step for step, _ in curved.curve]
    last = 6 * math.ceil(360 / 32)  # 6 epochs over the 360 training rows (40 held out)
    assert steps == [*range(0, last, 7), last]
    assert curved.curve[-1][1] >= curved.val_loss * (1 - 1e-9)  # the restored best is at most the last weights' error
    assert curved.curve[-1][1] < curved.curve[0][1]


def test_curve_every_is_checked() -> None:
    model = DynamicsModel(IdentityHead(), small_ensemble())
    with pytest.raises(ValueError, match="curve_every must be an int >= 0"):
        ModelTrainer(model, curve_every=-1)
