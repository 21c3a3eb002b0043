"""Planning with a learned model: the planners (CEM, iCEM, MPPI, :mod:`~pets.planning.planners`), what they score
(trajectory sampling and propagation, :mod:`~pets.planning.propagation` and :mod:`~pets.planning.particles`;
feedback candidates, :mod:`~pets.planning.feedback`; a learned terminal value, :mod:`~pets.planning.value`), the
cost estimate of a planning step (:mod:`~pets.planning.cost`) and open-loop planning
(:mod:`~pets.planning.openloop`)."""
