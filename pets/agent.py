"""The MPC agent: plan through the learned model (CEM, iCEM or MPPI), execute, shift the plan, replan."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from pets.planning.feedback import LinearFeedback
from pets.planning.planners import Planner, shift_plan
from pets.planning.propagation import TrajectoryEvaluator


class MPCAgent:
    """Model-predictive control over a planner.

    Every ``replan_every`` steps it plans a horizon-long action sequence from the current
    observation (warm-started with the previous plan shifted by the steps executed since)
    and executes its first actions. With ``feedback`` (:class:`pets.planning.feedback.LinearFeedback`) it plans the
    gains of a feedback law every step instead (warm-started with the last gains of the episode) and executes the law's
    action at the current observation.
    """

    def __init__(
        self,
        planner: Planner,
        evaluator: TrajectoryEvaluator,
        *,
        replan_every: int,
        action_low: np.ndarray,
        action_high: np.ndarray,
        device: torch.device,
        generator: torch.Generator,
        feedback: LinearFeedback | None = None,
    ) -> None:
        if feedback is not None and replan_every != 1:
            raise ValueError(
                f"feedback candidates are replanned every step: replan_every must be 1, got {replan_every}"
            )
        self.planner = planner
        self.feedback = feedback
        self.evaluator = evaluator
        self.replan_every = replan_every
        self.device = device
        self.generator = generator
        self._low = torch.as_tensor(action_low, dtype=torch.float32, device=device)
        self._high = torch.as_tensor(action_high, dtype=torch.float32, device=device)
        self.reset()

    def reset(self) -> None:
        """Forget the plan (call at the start of every episode)."""
        self._plan: Tensor | None = None
        self._step_in_plan = 0

    def act(self, obs: np.ndarray) -> np.ndarray:
        if self.feedback is not None:
            obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            self._plan = self.planner.plan(
                lambda gains: self.evaluator(obs_t, gains, self.generator), self._plan, self.generator
            )
            action = self.feedback.actions(self._plan.unsqueeze(0), obs_t.unsqueeze(0))[0]
            return action.detach().cpu().numpy().astype(np.float64)
        if self._plan is None or self._step_in_plan >= self.replan_every:
            init = None
            if self._plan is not None:
                init = self._plan
                for _ in range(self._step_in_plan):
                    init = shift_plan(init, self._low, self._high)
            obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)

            def objective(actions: Tensor) -> Tensor:
                return self.evaluator(obs_t, actions, self.generator)

            self._plan = self.planner.plan(objective, init, self.generator)
            self._step_in_plan = 0
        action = self._plan[self._step_in_plan]
        self._step_in_plan += 1
        return action.detach().cpu().numpy().astype(np.float64)
