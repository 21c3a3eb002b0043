"""The compiled training step of ``model.compile`` (:class:`CompiledStep`): forward, loss, gradient by
``torch.func`` and the Adam update in one ``torch.compile`` graph. :class:`pets.learning.trainer.ModelTrainer`
runs it on every full minibatch (its eager step stays the reference, docs/performance.md, "Training at the fast
preset")."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from dynamics.model import DynamicsModel


class _LossModule(nn.Module):
    """``model.member_loss`` with the regularisers as a module, for ``torch.func.functional_call``."""

    def __init__(self, model: DynamicsModel, logvar_bound_coef: float, bf16: bool) -> None:
        super().__init__()
        self.model = model
        self.logvar_bound_coef = logvar_bound_coef
        self.bf16 = bf16

    def forward(self, x: Tensor, y: Tensor, obs: Tensor, next_obs: Tensor) -> tuple[Tensor, Tensor]:
        member_loss = self.model.member_loss(x, y, obs, next_obs, bf16=self.bf16)
        return self.model.add_regularisers(member_loss.sum(), self.logvar_bound_coef), member_loss.detach().mean()


class CompiledStep:
    """One training step (forward, loss, gradient, Adam update) as one ``torch.compile`` graph.

    The gradient comes from ``torch.func.grad_and_value`` over the model's parameters, and the update is
    ``torch.optim.Adam``'s (no weight decay, no amsgrad) applied in place to the parameters and to the
    optimiser's own ``step``/``exp_avg``/``exp_avg_sq`` state, so checkpoints and the eager step keep working on
    the same optimiser. Called with (E, B, .) batches; returns the detached mean member loss (no host sync).
    Compiled lazily on the first call, once per trainer: the shapes are fixed, so later calls (and trials) reuse it.
    """

    def __init__(
        self,
        model: DynamicsModel,
        optimizer: torch.optim.Adam,
        logvar_bound_coef: float,
        bf16: bool,
        backend: str | Callable,
    ) -> None:
        group = optimizer.param_groups[0]
        if len(optimizer.param_groups) != 1 or group["weight_decay"] or group["amsgrad"] or group["maximize"]:
            raise ValueError("CompiledStep supports one Adam parameter group without weight decay, amsgrad, maximize")
        self.optimizer = optimizer
        self.loss = _LossModule(model, logvar_bound_coef, bf16)
        self.names = [name for name, _ in self.loss.named_parameters()]
        self.params = [p for _, p in self.loss.named_parameters()]
        self._grad = torch.func.grad_and_value(
            lambda params, *batch: torch.func.functional_call(self.loss, params, batch), has_aux=True
        )
        self.compiled = torch.compile(self._step, backend=backend, dynamic=False)
        self._key: tuple | None = None  # hyperparameters and batch layout of the last call

    def state(self) -> tuple[list[Tensor], list[Tensor], list[Tensor]]:
        """The optimiser's per-parameter ``step``, ``exp_avg`` and ``exp_avg_sq`` (created as torch's Adam does)."""
        for p in self.params:
            st = self.optimizer.state[p]
            if not st:
                st["step"] = torch.tensor(0.0, dtype=torch.float32)
                st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        states = [self.optimizer.state[p] for p in self.params]
        return [s["step"] for s in states], [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states]

    def _step(
        self,
        params: list[Tensor],
        steps: list[Tensor],
        exp_avgs: list[Tensor],
        exp_avg_sqs: list[Tensor],
        lr: float,
        beta1: float,
        beta2: float,
        eps: float,
        x: Tensor,
        y: Tensor,
        obs: Tensor,
        next_obs: Tensor,
    ) -> Tensor:
        grads, (_, mean_loss) = self._grad(dict(zip(self.names, params)), x, y, obs, next_obs)
        with torch.no_grad():
            for p, g, step, m, v in zip(params, grads.values(), steps, exp_avgs, exp_avg_sqs):
                step.add_(1)
                m.lerp_(g, 1 - beta1)
                v.mul_(beta2).addcmul_(g, g, value=1 - beta2)
                bias1, bias2 = 1 - beta1**step, 1 - beta2**step
                p.addcdiv_(m, (v.sqrt() / bias2.sqrt() + eps) * (bias1 / lr), value=-1.0)
        return mean_loss

    def __call__(self, x: Tensor, y: Tensor, obs: Tensor, next_obs: Tensor) -> Tensor:
        group = self.optimizer.param_groups[0]
        hyper = (float(group["lr"]), *group["betas"], group["eps"])
        args = (self.params, *self.state(), *hyper, x, y, obs, next_obs)
        key = (hyper, *((t.shape, t.stride(), t.dtype, t.device) for t in (x, y, obs, next_obs)))
        if key != self._key:  # a first call, or new hyperparameters or batch shapes: guards on (may compile)
            out = self.compiled(*args)
            self._key = key
            return out
        # The same function on inputs of the same shapes as the last call: dynamo's guards (~0.5-2 ms a call at
        # these shapes, for ~50 tensors and the module) only re-check what ``key`` does.
        with torch.compiler.set_stance(skip_guard_eval_unsafe=True):
            return self.compiled(*args)
