"""Member networks: ensembles of Gaussian or deterministic MLPs, all members in one batched pass, with normalisers.

All members are evaluated at once: every layer stores its weights stacked as an
``(E, in, out)`` parameter and its bias as ``(E, 1, out)``, and a layer is one
``torch.baddbmm``. Each member outputs a mean and a soft-bounded log-variance per
target dimension. Inputs are normalised inside the module with a mean/std fitted on
the data (``fit_normaliser``), stored as buffers so they travel with ``state_dict``.

The pieces every PETS dynamics model shares live here too: :class:`MemberEnsemble` (normaliser,
elites, member selection) and the batched-member MLP helpers :func:`init_member_layers`,
:func:`member_mlp` and :func:`decay_loss`; the deterministic models of ``pets.models`` and
``gem_head.two_stage`` are built from them.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dynamics import fused

#: Per-layer L2 coefficients of the original PETS code (input layer, hidden layers, output layer).
_DECAY_FIRST, _DECAY_SECOND, _DECAY_HIDDEN, _DECAY_OUT = 2.5e-5, 5e-5, 7.5e-5, 1e-4


def layer_decays(num_linear: int) -> list[float]:
    """Weight-decay coefficient per linear layer: 2.5e-5, 5e-5, 7.5e-5, ..., 7.5e-5, 1e-4.

    With 4 hidden layers (5 linear layers) this is exactly the original PETS list
    (2.5e-5, 5e-5, 7.5e-5, 7.5e-5, 1e-4).
    """
    if num_linear == 1:
        return [_DECAY_OUT]
    hidden = [_DECAY_FIRST, _DECAY_SECOND] + [_DECAY_HIDDEN] * max(0, num_linear - 3)
    return hidden[: num_linear - 1] + [_DECAY_OUT]


def init_member_layers(sizes: list[int], ensemble_size: int) -> tuple[nn.ParameterList, nn.ParameterList]:
    """Stacked per-member linear layers ``sizes[0] -> sizes[1] -> ... -> sizes[-1]``.

    Weights ``(E, fan_in, fan_out)`` from a truncated normal (std ``1 / (2 sqrt(fan_in))``, cut at 2 std),
    biases ``(E, 1, fan_out)`` zero: the initialisation of the original PETS code.
    """
    weights, biases = nn.ParameterList(), nn.ParameterList()
    for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
        w = torch.empty(ensemble_size, fan_in, fan_out)
        std = 1.0 / (2.0 * math.sqrt(fan_in))
        nn.init.trunc_normal_(w, mean=0.0, std=std, a=-2.0 * std, b=2.0 * std)
        weights.append(nn.Parameter(w))
        biases.append(nn.Parameter(torch.zeros(ensemble_size, 1, fan_out)))
    return weights, biases


#: Hidden-layer activations (``model.activation``): name -> (the torch function, oneDNN's post-op name for
#: :mod:`dynamics.fused`). SiLU (swish) is PETS' and the GEM paper's; ReLU costs a fraction of its ``exp``
#: (docs/performance.md, "The activation").
ACTIVATIONS = {"silu": (F.silu, "swish"), "relu": (F.relu, "relu")}


def check_activation(activation: str) -> None:
    """ValueError unless ``activation`` is a key of :data:`ACTIVATIONS`."""
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {', '.join(ACTIVATIONS)}, got {activation!r}")


#: Inference pads the output layer's width up to a multiple of this (see :func:`member_mlp`).
GEMM_WIDTH_MULTIPLE = 8


def member_mlp(
    h: Tensor, weights: nn.ParameterList, biases: nn.ParameterList, idx: Tensor | None, activation: str = "silu"
) -> Tensor:
    """Run all (or the ``idx``-selected) members' MLPs at once: ``activation`` (:data:`ACTIVATIONS`) between layers,
    linear output.

    ``h`` is (B, in), shared by the members (one broadcast matmul per layer), or (M, B, in), one batch per
    member (one ``baddbmm`` per layer). Returns (M, B, out).

    Without autograd (planning, evaluation), an output layer whose width is not a multiple of
    ``GEMM_WIDTH_MULTIPLE`` runs with its weights and bias zero-padded to the next multiple and the
    extra columns are dropped (a view; callers slice mean and log-variance out of it anyway): MKL's
    batched fp32 GEMM is up to 1.5x slower for such widths (200 -> 214, the GEM head's Ant output:
    12.0 ms vs 8.1 ms for 216, 5 members x 1600 rows). The kept columns are the same dot products
    (bit-identical on the machine tested; tests/test_ensemble.py). Training (autograd on) runs unpadded.

    Under CPU bf16 autocast without autograd the layers run as oneDNN fused linear + activation calls, one member
    at a time (:mod:`dynamics.fused`: measured faster there).
    """
    act, post_op = ACTIVATIONS[activation]
    if fused.applies(h):
        return fused.fused_member_mlp(h, weights, biases, idx, post_op)
    last = len(weights) - 1
    pad_widths = not torch.is_grad_enabled()
    prepared = None
    if pad_widths:  # planning: the selected, padded, cast weights once per evaluator call (dynamics.fused)
        device = h.device.type
        dtype = torch.get_autocast_dtype(device) if torch.is_autocast_enabled(device) else weights[0].dtype
        prepared = fused.batched_layers(weights, biases, idx, dtype, GEMM_WIDTH_MULTIPLE)
    for i, (w, b) in enumerate(zip(weights, biases)):
        width = w.shape[-1]
        pad = -width % GEMM_WIDTH_MULTIPLE if pad_widths and i == last else 0
        if prepared is not None:
            w, b = prepared[i]
        else:
            if idx is not None:
                w, b = w.index_select(0, idx), b.index_select(0, idx)
            if pad:
                w, b = F.pad(w, (0, pad)), F.pad(b, (0, pad))
        if h.dim() == 2:  # shared inputs: one broadcast matmul gives (M, B, out)
            h = torch.matmul(h, w) + b
        else:
            h = torch.baddbmm(b, h, w)
        if pad:
            h = h[..., :width]
        if i < last:
            h = act(h)
    return h


def check_member_args(**values: int) -> None:
    """ValueError unless every value is a positive int (``num_layers`` may be 0)."""
    for name, value in values.items():
        low = 0 if name == "num_layers" else 1
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            what = "an int >= 0" if low == 0 else "a positive int"
            raise ValueError(f"{name}{' (hidden layers)' if low == 0 else ''} must be {what}, got {value!r}")


class MemberEnsemble(nn.Module, ABC):
    """What every member network shares: input and target normalisers, elites and member selection.

    Subclasses build their batched-member layers (:func:`init_member_layers`, :func:`member_mlp`),
    implement ``forward(x, members=None) -> (mean, logvar)`` (each (M, B, out_dim)), ``member_parameters``,
    ``weight_decay_loss`` and ``logvar_bound_penalty``, and set ``deterministic`` (True: the
    log-variance is a constant that makes the sampling noise exactly zero, see docs/models.md).

    Buffers: ``input_mean``, ``input_std`` (input normaliser), ``target_mean``, ``target_std`` (target
    normaliser: the networks predict standardised targets, ``forward`` returns them in target units) and
    ``elites`` (long indices of the elite members, all members until a trainer sets them).
    """

    #: True for networks without a predictive variance; the Gaussian ensemble has one.
    deterministic: bool = False
    #: Whether ``logvar_bound_penalty`` has trainable terms (the trainer adds it to the loss only then).
    learn_logvar_bounds: bool = False

    def __init__(
        self, in_dim: int, out_dim: int, ensemble_size: int, num_elites: int | None, activation: str = "silu"
    ) -> None:
        super().__init__()
        check_activation(activation)
        if num_elites is None:
            num_elites = ensemble_size
        if not isinstance(num_elites, int) or not 1 <= num_elites <= ensemble_size:
            raise ValueError(f"num_elites must be an int in [1, ensemble_size={ensemble_size}], got {num_elites!r}")
        self.in_dim = in_dim
        self.out_dim = out_dim
        self.ensemble_size = ensemble_size
        self.num_elites = num_elites
        #: Hidden-layer activation, a key of :data:`ACTIVATIONS`.
        self.activation = activation
        self.register_buffer("input_mean", torch.zeros(in_dim))
        self.register_buffer("input_std", torch.ones(in_dim))
        self.register_buffer("target_mean", torch.zeros(out_dim))
        self.register_buffer("target_std", torch.ones(out_dim))
        self.register_buffer("elites", torch.arange(ensemble_size, dtype=torch.long))

    # ------------------------------------------------------------------ normaliser
    @torch.no_grad()
    def fit_normaliser(self, x: Tensor) -> None:
        """Set the input mean/std from raw inputs ``x`` of shape (N, in_dim); a std < 1e-5 becomes 1."""
        if x.dim() != 2 or x.shape[1] != self.in_dim or x.shape[0] < 1:
            raise ValueError(
                f"fit_normaliser expects raw inputs of shape (N >= 1, in_dim={self.in_dim}), got {tuple(x.shape)}"
            )
        if not torch.isfinite(x).all():
            raise ValueError("fit_normaliser got non-finite inputs (nan or inf)")
        mean, std = column_mean_std(x)
        self.input_mean.copy_(mean.to(self.input_mean))
        self.input_std.copy_(std.to(self.input_std))

    def normalise(self, x: Tensor) -> Tensor:
        """``(x - input_mean) / input_std`` (broadcast over leading dims)."""
        return (x - self.input_mean) / self.input_std

    @torch.no_grad()
    def fit_target_normaliser(self, y: Tensor) -> None:
        """Set the target mean/std from training targets ``y`` of shape (N, out_dim); a std < 1e-5 becomes 1."""
        if y.dim() != 2 or y.shape[1] != self.out_dim or y.shape[0] < 1:
            raise ValueError(
                f"fit_target_normaliser expects targets of shape (N >= 1, out_dim={self.out_dim}), got {tuple(y.shape)}"
            )
        if not torch.isfinite(y).all():
            raise ValueError("fit_target_normaliser got non-finite targets (nan or inf)")
        mean, std = column_mean_std(y)
        self.target_mean.copy_(mean.to(self.target_mean))
        self.target_std.copy_(std.to(self.target_std))

    def denormalise_target(self, z: Tensor) -> Tensor:
        """``target_mean + target_std * z``: standardised network outputs in target units."""
        return torch.addcmul(self.target_mean, z, self.target_std)

    # ------------------------------------------------------------------ elites
    def set_elites(self, elites: Tensor) -> None:
        """Store the elite member indices (1-D, unique, in ``[0, ensemble_size)``)."""
        elites = torch.as_tensor(elites, dtype=torch.long).flatten()
        if (
            elites.numel() < 1
            or int(elites.min()) < 0
            or int(elites.max()) >= self.ensemble_size
            or torch.unique(elites).numel() != elites.numel()
        ):
            raise ValueError(
                f"elites must be unique member indices in [0, {self.ensemble_size}), got {elites.tolist()}"
            )
        self.elites = elites.to(self.input_mean.device)

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        if prefix + "input_mean" in state_dict and prefix + "target_mean" not in state_dict:
            raise ValueError(
                "this checkpoint was written before models standardised their targets (gem-pets < 0.2): "
                "its networks predict other units; train the model again"
            )
        # The number of elites may differ from the freshly built default: adopt the stored shape.
        key = prefix + "elites"
        if key in state_dict and state_dict[key].shape != self.elites.shape:
            self.elites = torch.empty_like(state_dict[key], device=self.elites.device, dtype=torch.long)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    # ------------------------------------------------------------------ forward helpers
    @abstractmethod
    def member_parameters(self) -> list[Tensor]:
        """Parameters with a leading member dimension (weights and biases), in a fixed order."""

    @abstractmethod
    def forward(self, x: Tensor, members: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Mean and log-variance (M, B, out_dim) of raw inputs (B, in_dim) or (M, B, in_dim), in target units."""

    @abstractmethod
    def weight_decay_loss(self) -> Tensor:
        """The L2 penalty of the member weights."""

    @abstractmethod
    def logvar_bound_penalty(self) -> Tensor:
        """The penalty of the learnt log-variance bounds (zero where there are none)."""

    def _member_index(self, members: Tensor | None) -> Tensor | None:
        if members is None:
            return None
        if not isinstance(members, Tensor):
            members = torch.as_tensor(members)
        if members.dim() != 1 or members.dtype not in (torch.int64, torch.int32) or members.numel() < 1:
            raise ValueError(
                f"members must be a non-empty 1-D integer tensor of member indices, "
                f"got shape {tuple(members.shape)} dtype {members.dtype}"
            )
        return members.to(device=self.input_mean.device, dtype=torch.long)

    def _check_inputs(self, x: Tensor, members: Tensor | None) -> tuple[Tensor | None, int]:
        """(member index or None, M) after checking that ``x`` is (B, in_dim) or (M, B, in_dim)."""
        idx = self._member_index(members)
        m = self.ensemble_size if idx is None else idx.numel()
        if x.dim() not in (2, 3) or x.shape[-1] != self.in_dim or (x.dim() == 3 and x.shape[0] != m):
            raise ValueError(
                f"inputs must be (B, {self.in_dim}) or ({m}, B, {self.in_dim}) for {m} members, got {tuple(x.shape)}"
            )
        return idx, m


def column_mean_std(x: Tensor) -> tuple[Tensor, Tensor]:
    """Column mean and std (float64, population std) of ``x`` (N, D); a std < 1e-5 becomes 1."""
    x64 = x.detach().to(torch.float64)
    mean = x64.mean(dim=0)
    std = x64.std(dim=0, correction=0)
    return mean, torch.where(std < 1e-5, torch.ones_like(std), std)


def decay_loss(weights: nn.ParameterList, decays: list[float]) -> Tensor:
    """sum_l decay_l * 0.5 * ||W_l||^2 over the stacked weights (all members, no biases)."""
    total = weights[0].new_zeros(())
    for decay, w in zip(decays, weights):
        total = total + decay * 0.5 * w.pow(2).sum()
    return total


class GaussianEnsemble(MemberEnsemble):
    """``ensemble_size`` independent Gaussian MLPs ``x -> (mean, logvar)`` evaluated in one batched pass.

    Architecture per member: ``num_layers`` hidden layers of ``hidden_size`` SiLU units, then a
    linear output of ``2 * out_dim`` (mean and raw log-variance of the standardised target). The
    log-variance is soft-bounded in standardised units: ``lv = max_lv - softplus(max_lv - lv)``;
    ``lv = min_lv + softplus(lv - min_lv)``; ``forward`` returns mean and log-variance in target units
    (``target_mean + target_std * mean``, ``lv + 2 log target_std``).
    """

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        ensemble_size: int = 7,
        hidden_size: int = 200,
        num_layers: int = 4,
        min_logvar: float = -10.0,
        max_logvar: float = 0.5,
        learn_logvar_bounds: bool = True,
        num_elites: int | None = None,
        activation: str = "silu",
    ) -> None:
        check_member_args(
            in_dim=in_dim, out_dim=out_dim, ensemble_size=ensemble_size, hidden_size=hidden_size, num_layers=num_layers
        )
        if not (math.isfinite(min_logvar) and math.isfinite(max_logvar) and min_logvar < max_logvar):
            raise ValueError(f"need finite min_logvar < max_logvar, got min {min_logvar}, max {max_logvar}")
        super().__init__(in_dim, out_dim, ensemble_size, num_elites, activation)
        self.hidden_size = hidden_size
        self.num_layers = num_layers
        self.learn_logvar_bounds = learn_logvar_bounds

        sizes = [in_dim] + [hidden_size] * num_layers + [2 * out_dim]
        self.weights, self.biases = init_member_layers(sizes, ensemble_size)
        self.decays: list[float] = layer_decays(len(sizes) - 1)

        max_lv = torch.full((out_dim,), float(max_logvar))
        min_lv = torch.full((out_dim,), float(min_logvar))
        if learn_logvar_bounds:
            self.max_logvar = nn.Parameter(max_lv)
            self.min_logvar = nn.Parameter(min_lv)
        else:
            self.register_buffer("max_logvar", max_lv)
            self.register_buffer("min_logvar", min_lv)

    # ------------------------------------------------------------------ forward
    def member_parameters(self) -> list[Tensor]:
        """Parameters with a leading member dimension (weights and biases), in a fixed order."""
        return [*self.weights, *self.biases]

    def forward(self, x: Tensor, members: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Mean and log-variance, each (M, B, out_dim), of raw (unnormalised) inputs.

        ``x`` is (M, B, in_dim), one batch per evaluated member, or (B, in_dim), shared by all of
        them. M is ``ensemble_size`` when ``members`` is None, else ``len(members)`` (members are
        gathered from the stacked weights by index, e.g. the elites).
        """
        idx, _ = self._check_inputs(x, members)
        # bf16 layers (autocast) return bf16: one exact cast, so that the tail below runs on float32 alone.
        h = member_mlp(self.normalise(x), self.weights, self.biases, idx, self.activation).to(self.target_mean.dtype)
        mean, logvar = h[..., : self.out_dim], h[..., self.out_dim :]
        return self.denormalise_target(mean), self.bound_logvar(logvar) + 2.0 * self.target_std.log()

    def bound_logvar(self, logvar: Tensor) -> Tensor:
        """Soft bounds on the standardised log-variance: lv = max - softplus(max - lv), then
        lv = min + softplus(lv - min)."""
        logvar = self.max_logvar - F.softplus(self.max_logvar - logvar)
        return self.min_logvar + F.softplus(logvar - self.min_logvar)

    # ------------------------------------------------------------------ regularisers
    def weight_decay_loss(self) -> Tensor:
        """Per-layer L2 penalty of the original PETS: sum_l decay_l * 0.5 * ||W_l||^2 (all members, no biases)."""
        return decay_loss(self.weights, self.decays)

    def logvar_bound_penalty(self) -> Tensor:
        """``sum(max_logvar) - sum(min_logvar)``: the original adds 0.01 times this to the loss."""
        return self.max_logvar.sum() - self.min_logvar.sum()

    def extra_repr(self) -> str:
        return (
            f"in_dim={self.in_dim}, out_dim={self.out_dim}, ensemble_size={self.ensemble_size}, "
            f"hidden_size={self.hidden_size}, num_layers={self.num_layers}, num_elites={self.num_elites}, "
            f"activation={self.activation}, learn_logvar_bounds={self.learn_logvar_bounds}"
        )


#: Log-variance a deterministic model reports: exp(0.5 * -2000) == 0 exactly in every float dtype.
DETERMINISTIC_LOGVAR = -2000.0


class DeterministicEnsemble(MemberEnsemble):
    """``ensemble_size`` independent MLPs ``x -> mean`` evaluated in one batched pass, no variance.

    Architecture per member: ``num_layers`` hidden layers of ``hidden_size`` SiLU units, then a linear output
    of ``out_dim``; the same batched layers, initialisation, input normaliser and per-layer weight decay as
    :class:`GaussianEnsemble`. ``forward`` returns ``(mean, logvar)`` with ``logvar`` filled with
    :data:`DETERMINISTIC_LOGVAR`, so PETS' sampling ``mean + exp(logvar / 2) eps`` returns ``mean`` exactly.
    """

    deterministic = True

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        ensemble_size: int = 5,
        hidden_size: int = 200,
        num_layers: int = 4,
        num_elites: int | None = None,
        activation: str = "silu",
    ) -> None:
        check_member_args(
            in_dim=in_dim, out_dim=out_dim, ensemble_size=ensemble_size, hidden_size=hidden_size, num_layers=num_layers
        )
        super().__init__(in_dim, out_dim, ensemble_size, num_elites, activation)
        self.hidden_size = hidden_size
        self.num_layers = num_layers
        sizes = [in_dim] + [hidden_size] * num_layers + [out_dim]
        self.weights, self.biases = init_member_layers(sizes, ensemble_size)
        self.decays: list[float] = layer_decays(len(sizes) - 1)

    def member_parameters(self) -> list[Tensor]:
        """Parameters with a leading member dimension (weights and biases), in a fixed order."""
        return [*self.weights, *self.biases]

    def forward(self, x: Tensor, members: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Mean (M, B, out_dim) of raw inputs ``x`` ((B, in_dim) shared, or (M, B, in_dim)) and the constant
        log-variance :data:`DETERMINISTIC_LOGVAR` of the same shape."""
        idx, _ = self._check_inputs(x, members)
        mean = self.denormalise_target(member_mlp(self.normalise(x), self.weights, self.biases, idx, self.activation))
        return mean, torch.full_like(mean, DETERMINISTIC_LOGVAR)

    def weight_decay_loss(self) -> Tensor:
        """Per-layer L2 penalty of the original PETS: sum_l decay_l * 0.5 * ||W_l||^2 (all members, no biases)."""
        return decay_loss(self.weights, self.decays)

    def logvar_bound_penalty(self) -> Tensor:
        """Zero: there is no log-variance to bound."""
        return self.weights[0].new_zeros(())

    def extra_repr(self) -> str:
        return (
            f"in_dim={self.in_dim}, out_dim={self.out_dim}, ensemble_size={self.ensemble_size}, "
            f"hidden_size={self.hidden_size}, num_layers={self.num_layers}, num_elites={self.num_elites}, "
            f"activation={self.activation}, deterministic=True"
        )
