"""The dynamics model: observation and action in, next observation out (head + network + normalisers)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from dynamics.heads import DynamicsHead
from dynamics.networks import MemberEnsemble


class DynamicsModel(nn.Module):
    """One object from observations to predictions: the head encodes ``(obs, act)`` into network inputs and
    ``(obs, next_obs)`` into targets, the member network predicts a Gaussian (or deterministic) target per
    member, and the head decodes a target into the next observation.

    Every consumer (trainer, trajectory sampling, evaluation, open-loop planning, the benchmark) goes through
    these methods. ``state_dict`` holds the network with its normalisers and elites (the head is stateless,
    rebuilt from the config).
    """

    def __init__(self, head: DynamicsHead, network: MemberEnsemble, name: str | None = None) -> None:
        """``name``: the model's name (``--model``; ``pets.models.make_model`` passes it), else the head's."""
        super().__init__()
        if head.input_dim != network.in_dim or head.target_dim != network.out_dim:
            raise ValueError(
                f"head {head.name!r} has input_dim {head.input_dim} / target_dim {head.target_dim} but the "
                f"network has in_dim {network.in_dim} / out_dim {network.out_dim}"
            )
        if head.deterministic != network.deterministic:  # the one place the two declarations must agree
            kind = {True: "deterministic", False: "Gaussian"}
            raise ValueError(
                f"head {head.name!r} is {kind[head.deterministic]} but the network "
                f"{type(network).__name__} is {kind[network.deterministic]}: a deterministic head (loss without "
                "logvar) needs a network without a predictive variance, and a Gaussian head one with it"
            )
        self.head = head
        self.network = network
        self._name = name

    # ------------------------------------------------------------------ facts
    @property
    def name(self) -> str:
        """The model's ``--model`` name (a model of one's own: its registered name, whatever head it reuses)."""
        return self._name or self.head.name

    @property
    def obs_dim(self) -> int:
        return self.head.obs_dim

    @property
    def act_dim(self) -> int:
        return self.head.act_dim

    @property
    def target_dim(self) -> int:
        return self.head.target_dim

    @property
    def deterministic(self) -> bool:
        """True for models without a predictive variance (their sampling noise is exactly zero); the head and the
        network agree on it (checked when the model is made)."""
        return self.network.deterministic

    @property
    def ensemble_size(self) -> int:
        return self.network.ensemble_size

    @property
    def elites(self) -> Tensor:
        """Long indices of the elite members (all members until a trainer sets them)."""
        return self.network.elites

    def set_elites(self, elites: Tensor) -> None:
        self.network.set_elites(elites)

    # ------------------------------------------------------------------ encoding / decoding
    def inputs(self, obs: Tensor, act: Tensor) -> Tensor:
        """Network inputs (..., in_dim) of observations and actions."""
        return self.head.inputs(obs, act)

    def targets(self, obs: Tensor, next_obs: Tensor) -> Tensor:
        """Training targets (..., target_dim) of transitions."""
        return self.head.targets(obs, next_obs)

    def next_obs(self, obs: Tensor, target: Tensor) -> Tensor:
        """Next observation (..., obs_dim) from a predicted or sampled target."""
        return self.head.next_obs(obs, target)

    # ------------------------------------------------------------------ prediction
    def forward(self, x: Tensor, members: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Mean and log-variance of the target, each (M, B, target_dim), of network inputs ``x`` ((B, in) shared by
        the members or (M, B, in)); M is ``ensemble_size`` or ``len(members)``."""
        return self.network(x, members)

    def _as_model_tensor(self, x: Any, what: str = "input") -> Tensor:
        """``x`` (numpy, torch or a nested list of numbers) as a tensor on the model's device and dtype; ValueError
        (one line) for anything that is not an array of numbers (a string, a ragged list, objects)."""
        ref = self.member_parameters()[0]
        if not isinstance(x, Tensor):
            given = type(x).__name__
            try:
                x = np.asarray(x)
            except ValueError as err:  # a ragged nested list
                raise ValueError(f"{what} must be an array of numbers, got a ragged {given} ({err})") from None
            if x.dtype.kind not in "biuf":
                raise ValueError(f"{what} must be an array of numbers, got a {given} of {x.dtype} values")
        elif x.is_complex():
            raise ValueError(f"{what} must be an array of real numbers, got {x.dtype}")
        return torch.as_tensor(x, device=ref.device).to(ref.dtype)

    @torch.no_grad()
    def predict(
        self, obs: Any, act: Any, mode: str = "mean", generator: torch.Generator | None = None
    ) -> np.ndarray | Tensor:
        """Next observations (..., obs_dim) of observations (..., obs_dim) and actions (..., act_dim), batched over
        any leading dims: numpy in, numpy out; torch in, torch out. ``mode`` as in :meth:`rollout`."""
        act = act if isinstance(act, Tensor) else self._as_model_tensor(act, "actions").cpu().numpy()
        if act.ndim == 0:
            raise ValueError(f"expected actions (..., {self.act_dim}), got a single number")
        obs = obs if isinstance(obs, Tensor) else self._as_model_tensor(obs, "observations").cpu().numpy()
        obs_shape = tuple(obs.shape)
        if obs_shape[-1:] != (self.obs_dim,) or act.shape[-1] != self.act_dim:  # the shapes given, not rollout's
            raise ValueError(
                f"expected observations (..., {self.obs_dim}) and actions (..., {self.act_dim}), got "
                f"{obs_shape} and {tuple(act.shape)}"
            )
        if obs_shape[:-1] != tuple(act.shape[:-1]):
            raise ValueError(f"observations {obs_shape} and actions {tuple(act.shape)}: batch dims differ")
        return self.rollout(obs, act[..., None, :], mode, generator)[..., 0, :]

    #: Open-loop rollout modes of :meth:`rollout`.
    ROLLOUT_MODES = ("mean", "sample")

    @torch.no_grad()
    def rollout(
        self, obs0: Any, actions: Any, mode: str = "mean", generator: torch.Generator | None = None
    ) -> Tensor | np.ndarray:
        """Open-loop predicted observations (K, H, obs_dim) from start observations (K, obs_dim) under actions
        (K, H, act_dim), through the elite members. Numpy in, numpy out (the observations' type decides); any
        leading dims instead of K.

        ``mean``: the target is the mean over the elites of their predicted means. ``sample``: each row draws one
        elite once (TS-inf) and samples from its Gaussian every step. (Planning rolls out particles with rewards in
        ``pets.planning.propagation``.)
        """
        if mode not in self.ROLLOUT_MODES:
            raise ValueError(f"mode must be one of {self.ROLLOUT_MODES}, got {mode!r}")
        numpy_in = not isinstance(obs0, Tensor)
        obs0, actions = self._as_model_tensor(obs0, "observations"), self._as_model_tensor(actions, "actions")
        if obs0.dim() < 1 or actions.dim() < 2 or obs0.shape[-1] != self.obs_dim or actions.shape[-1] != self.act_dim:
            raise ValueError(
                f"expected observations (..., {self.obs_dim}) and actions (..., H, {self.act_dim}), got "
                f"{tuple(obs0.shape)} and {tuple(actions.shape)}"
            )
        if obs0.shape[:-1] != actions.shape[:-2]:
            missing_h = actions.shape[:-1] == obs0.shape[:-1]  # (K, act_dim) for (K, H, act_dim): no horizon axis
            raise ValueError(
                f"observations {tuple(obs0.shape)} and actions {tuple(actions.shape)}: "
                + (
                    "actions need a horizon axis, (..., H, act_dim); predict takes one step"
                    if missing_h
                    else "batch dims differ"
                )
            )
        if actions.shape[-2] == 0:
            raise ValueError(f"actions {tuple(actions.shape)} have no steps: a rollout needs a horizon H >= 1")
        for what, x in (("observations", obs0), ("actions", actions)):
            if not torch.isfinite(x).all():
                raise ValueError(f"{what} hold nan or inf; the model predicts from finite inputs only")
        if generator is not None and not isinstance(generator, torch.Generator):
            raise ValueError(f"generator must be a torch.Generator (or None), got {type(generator).__name__}")
        batch = obs0.shape[:-1]
        obs0, actions = obs0.reshape(-1, self.obs_dim), actions.reshape(-1, *actions.shape[-2:])
        out = self._rollout(obs0, actions, mode, generator).reshape(*batch, actions.shape[1], self.obs_dim)
        return out.cpu().numpy() if numpy_in else out

    def _rollout(self, obs0: Tensor, actions: Tensor, mode: str, generator: torch.Generator | None) -> Tensor:
        elites = self.elites.to(device=obs0.device, dtype=torch.long)
        k, horizon = actions.shape[:2]
        rows = torch.arange(k, device=obs0.device)
        if mode == "sample":
            member = torch.randint(elites.numel(), (k,), generator=generator, device=obs0.device)
        obs, preds = obs0, []
        for step in range(horizon):
            mean, logvar = self(self.inputs(obs, actions[:, step]), elites)  # (M, K, D)
            if mode == "mean":
                target = mean.mean(dim=0)
            else:
                mu, lv = mean[member, rows], logvar[member, rows]
                eps = torch.randn(mu.shape, generator=generator, device=mu.device, dtype=mu.dtype)
                target = mu + torch.exp(0.5 * lv) * eps
            obs = self.next_obs(obs, target)
            preds.append(obs)
        return torch.stack(preds, dim=1)

    # ------------------------------------------------------------------ training
    def fit_normalisers(self, x: Tensor, y: Tensor) -> None:
        """Fit the network's input and target normalisers on inputs ``x`` (N, in) and targets ``y`` (N, target)."""
        self.network.fit_normaliser(x)
        self.network.fit_target_normaliser(y)

    def member_loss(self, x: Tensor, y: Tensor, obs: Tensor, next_obs: Tensor, bf16: bool = False) -> Tensor:
        """Per-member training loss (E,) of (E, B, .) batches (the head's loss, in standardised units).

        ``bf16``: the network's forward (and so its backward) under bfloat16 autocast; its outputs are cast
        back to float32 at once, so the loss is computed in float32 against float32 weights.
        """
        with torch.autocast(device_type=x.device.type, dtype=torch.bfloat16, enabled=bf16):
            mean, logvar = self.network(x)
        if bf16:
            mean, logvar = mean.float(), logvar.float()
        return self.head.loss(mean, logvar, y, obs, next_obs, scale=self.network.target_std)

    def add_regularisers(self, loss: Tensor, logvar_bound_coef: float) -> Tensor:
        """``loss`` + weight decay (+ ``logvar_bound_coef`` times the log-variance bound penalty where the bounds
        are learnt)."""
        loss = loss + self.network.weight_decay_loss()
        if self.network.learn_logvar_bounds and logvar_bound_coef:
            loss = loss + logvar_bound_coef * self.network.logvar_bound_penalty()
        return loss

    def member_parameters(self) -> list[Tensor]:
        """Parameters with a leading member dimension (snapshotted per member by early stopping)."""
        return self.network.member_parameters()

    def extra_repr(self) -> str:
        return f"name={self.name!r}"
