"""The two choices of a trajectory evaluator as small strategy objects (``pets.planning.propagation``).

A propagation mode (``planner.propagation``, :data:`PROPAGATION_TABLE`) is a :class:`RowLayout` (how the rows of the
particles are arranged for the ensemble, which member each row uses, how the members' predictions are combined)
with a :class:`Noise` (whether the next target is sampled from the predicted Gaussian):

- ``ts1``: :class:`Shuffled` rows (a fresh random permutation per step), :class:`Gaussian` noise;
- ``tsinf``: :class:`MemberMajor` rows (each particle keeps one member), :class:`Gaussian` noise;
- ``members``: :class:`MemberMajor` rows, :class:`NoNoise` (each row follows its member's mean);
- ``expectation``: :class:`Shared` rows (one per candidate, every member sees it, their means averaged), no noise.

A mode of one's own is one :func:`register_propagation` call, in a module named in the config key ``imports``.

A candidate kind (``planner.candidates``, :data:`CANDIDATE_TABLE`) says what a candidate is: :class:`OpenLoop`, an
action sequence (N, H, act_dim); :class:`FeedbackGains`, the gains (N, rows, act_dim) of a
:class:`pets.planning.feedback.LinearFeedback` rolled out for its horizon; each kind owns its checks of the
config (``check_config``), its law (``make_law``), whether every planner searches it (``searches_actions``) and its
own settings (``section``: a dataclass, the config's ``planner.<kind>.*``, as a planner's). A kind of one's own is one
:func:`register_candidates` call, in a module named in the config key ``imports``.
Both choices are vectorised over all rows: a strategy adds no Python loop and no host synchronisation.
"""

from __future__ import annotations

from dataclasses import dataclass, is_dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import torch
from torch import Tensor

from dynamics.model import DynamicsModel
from pets.imports import definition
from pets.planning.feedback import FeedbackConfig, LinearFeedback, check_feedback

if TYPE_CHECKING:
    from envs import EnvSpec


@dataclass(frozen=True)
class Rows:
    """The rows of one evaluator call: ``b`` rows (padded), ``per_member`` rows of each member block, each row's
    candidate ``cand`` (b,), and the flat index of each natural row (``n * P + p``) where the layout reorders them."""

    b: int
    per_member: int
    cand: Tensor
    nat_to_flat: Tensor | None = None
    arange: Tensor | None = None  # 0..b-1, for the inverse of a permutation (Shuffled)


class RowLayout:
    """Candidate-major rows (``n * P + p``), padded up to a multiple of the members with rows that replay the last
    candidate; each member gets one block of consecutive rows."""

    def particles(self, particles: int) -> int:
        """Rows per candidate."""
        return particles

    def rows_per_member(self, candidates: int, particles: int, members: int) -> int:
        """Rows of each member's block in one model step of ``candidates`` candidates (the padding included)."""
        return -(-candidates * self.particles(particles) // members)

    def model_rows(self, candidates: int, particles: int, members: int) -> int:
        """(row, member) pairs one model step computes for ``candidates`` candidates (the padding left out): each
        row goes through one member."""
        return candidates * self.particles(particles)

    def arrange(self, n_cand: int, p_eff: int, m: int, device: torch.device) -> Rows:
        rows = n_cand * p_eff
        per_member = -(-rows // m)
        b = per_member * m
        flat = torch.arange(b, device=device)
        return Rows(b, per_member, torch.clamp(flat // p_eff, max=n_cand - 1))

    def draw(self, rows: Rows, generator: torch.Generator | None) -> tuple[Tensor | None, Tensor | None]:
        """This step's permutation of the rows and its inverse (None, None: the rows keep their order)."""
        return None, None

    def forward(self, model: DynamicsModel, inp: Tensor, members: Tensor | None, m: int) -> tuple[Tensor, Tensor]:
        """The ensemble on the rows: one (M, b / M, in) block per member."""
        return model(inp.reshape(m, inp.shape[0] // m, -1), members)

    def combine(self, target: Tensor, b: int) -> Tensor:
        """Each row's next target (b, target_dim) from the members' (M, b / M, target_dim)."""
        return target.reshape(b, -1)

    def natural(self, rows: Rows, x: Tensor, n_rows: int) -> Tensor:
        """``x`` (b, ...) in natural order, without the padding."""
        return x[:n_rows]


class Shuffled(RowLayout):
    """Candidate-major rows gathered into a fresh random permutation before the model every step, scattered back
    after: each row's member is uniform over the members, every member gets the same number of rows (TS1)."""

    def arrange(self, n_cand: int, p_eff: int, m: int, device: torch.device) -> Rows:
        rows = super().arrange(n_cand, p_eff, m, device)
        return Rows(rows.b, rows.per_member, rows.cand, arange=torch.arange(rows.b, device=device))

    def draw(self, rows: Rows, generator: torch.Generator | None) -> tuple[Tensor | None, Tensor | None]:
        perm = torch.randperm(rows.b, generator=generator, device=rows.cand.device)
        return perm, torch.empty_like(perm).scatter_(0, perm, rows.arange)


class MemberMajor(RowLayout):
    """Rows fixed for the whole rollout, member-major: particle ``p`` of candidate ``n`` (virtual row
    ``r = n * P + p``) uses member ``r % M`` and sits in slot ``(r % M) * per_member + r // M`` (no gather per
    step)."""

    def arrange(self, n_cand: int, p_eff: int, m: int, device: torch.device) -> Rows:
        rows = n_cand * p_eff
        per_member = -(-rows // m)
        b = per_member * m
        # Flat (slot) s = k * per_member + j holds virtual row r = j * m + k, which uses member k.
        slot = torch.arange(b, device=device)
        virtual = (slot % per_member) * m + slot // per_member
        cand = torch.clamp(virtual // p_eff, max=n_cand - 1)
        natural = torch.arange(rows, device=device)
        return Rows(b, per_member, cand, nat_to_flat=(natural % m) * per_member + natural // m)

    def natural(self, rows: Rows, x: Tensor, n_rows: int) -> Tensor:
        return x.index_select(0, rows.nat_to_flat)


class Shared(RowLayout):
    """One row per candidate, the same input for every member; the next target is the mean of the members' means
    (in target space). All particles would be alike, so there is one."""

    def particles(self, particles: int) -> int:
        return 1

    def rows_per_member(self, candidates: int, particles: int, members: int) -> int:
        return candidates  # every member sees every row

    def model_rows(self, candidates: int, particles: int, members: int) -> int:
        return candidates * members

    def arrange(self, n_cand: int, p_eff: int, m: int, device: torch.device) -> Rows:
        rows = n_cand * p_eff
        flat = torch.arange(rows, device=device)
        return Rows(rows, -(-rows // m), torch.clamp(flat // p_eff, max=n_cand - 1))

    def forward(self, model: DynamicsModel, inp: Tensor, members: Tensor | None, m: int) -> tuple[Tensor, Tensor]:
        return model(inp, members)  # (M, b, out), the input shared by the members

    def combine(self, target: Tensor, b: int) -> Tensor:
        return target.mean(dim=0)


class Noise:
    """How the next target comes from the predicted Gaussian; this base samples nothing (the mean)."""

    def buffer(self, shape: tuple[int, int, int], device: torch.device, dtype: torch.dtype) -> Tensor | None:
        """The call's noise buffer (refilled every step), or None."""
        return None

    def draw(self, noise: Tensor | None, generator: torch.Generator | None) -> None:
        """Refill the buffer with this step's noise."""

    def target(self, mean: Tensor, logvar: Tensor, noise: Tensor | None) -> Tensor:
        return mean


class NoNoise(Noise):
    """No sampling: the next target is the predicted mean."""


class Gaussian(Noise):
    """``target = mean + exp(0.5 * logvar) * eps``, ``eps ~ N(0, I)`` from the generator, one buffer refilled in
    place every step (the same stream as fresh draws)."""

    def buffer(self, shape: tuple[int, int, int], device: torch.device, dtype: torch.dtype) -> Tensor | None:
        return torch.empty(shape, device=device, dtype=dtype)

    def draw(self, noise: Tensor | None, generator: torch.Generator | None) -> None:
        torch.randn(noise.shape, generator=generator, device=noise.device, dtype=noise.dtype, out=noise)

    def target(self, mean: Tensor, logvar: Tensor, noise: Tensor | None) -> Tensor:
        return mean + torch.exp(0.5 * logvar) * noise


@dataclass(frozen=True)
class Propagation:
    """A propagation mode: its row layout and its noise."""

    layout: RowLayout
    noise: Noise


#: ``planner.propagation``: each mode's strategies (the module docstring).
PROPAGATION_TABLE: dict[str, Propagation] = {
    "ts1": Propagation(Shuffled(), Gaussian()),
    "tsinf": Propagation(MemberMajor(), Gaussian()),
    "expectation": Propagation(Shared(), NoNoise()),
    "members": Propagation(MemberMajor(), NoNoise()),
}


def _parts(propagation: Propagation) -> tuple[str, str]:
    """Where a mode's strategies are defined (:func:`pets.imports.definition`)."""
    return definition(propagation.layout), definition(propagation.noise)


def register_propagation(name: str, propagation: Propagation) -> Propagation:
    """Add ``propagation`` to :data:`PROPAGATION_TABLE` under ``name`` (a ``planner.propagation`` value from then
    on, from a module in the config key ``imports`` too); returns it. ValueError (one line) for a name that is not a
    non-empty str, one another mode holds, or a value that is not a :class:`Propagation` of a :class:`RowLayout`
    and a :class:`Noise`."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"a propagation's name must be a non-empty str, got {name!r}")
    ok = isinstance(propagation, Propagation) and isinstance(propagation.layout, RowLayout)
    if not (ok and isinstance(propagation.noise, Noise)):
        raise ValueError(f"propagation {name!r} must be a Propagation(RowLayout, Noise), got {propagation!r}")
    taken = PROPAGATION_TABLE.get(name)
    if taken is not None and _parts(taken) != _parts(propagation):  # the same strategies again: a module re-imported
        names = ", ".join(type(part).__qualname__ for part in (taken.layout, taken.noise))
        raise ValueError(f"propagation name {name!r} is taken ({names}); give yours another name")
    PROPAGATION_TABLE[name] = propagation
    return propagation


class OpenLoop:
    """Candidates are action sequences (N, H, act_dim), read time-major: every step one contiguous (b, A) block."""

    #: Whether a candidate is an action sequence, which every planner searches (False: the gains of a law, which only
    #: the planners with ``gain_options`` search).
    searches_actions: ClassVar[bool] = True
    #: The dataclass of this kind's own settings, the config's ``planner.<kind>.*`` (None: none).
    section: ClassVar[type | None] = None
    law: LinearFeedback | None = None

    def __init__(self, law: LinearFeedback | None = None) -> None:
        self.law = law  # what make_law built: None for a kind of action sequences

    @classmethod
    def build(cls, planner: Any, spec: EnvSpec, device: torch.device) -> OpenLoop:
        """This kind's strategy for the config's ``planner`` section: ``cls(make_law(...))``; a kind whose rollout
        reads settings of its own (its ``section``, ``planner.<kind>``) overrides it."""
        return cls(cls.make_law(planner, spec, device))

    @staticmethod
    def check_config(planner: Any) -> None:
        """This kind's checks of the config's ``planner`` section (a ValueError in one line): none."""

    @staticmethod
    def make_law(planner: Any, spec: EnvSpec, device: torch.device) -> LinearFeedback | None:
        """The law a candidate of this kind parametrises, from the config's ``planner`` section (None: none)."""
        return None

    def horizon(self, actions: Tensor) -> int:
        return actions.shape[1]

    def check(self, actions: Tensor) -> None:
        """A ValueError when ``actions`` are not candidates of this kind (beyond the (N, H, act_dim) checks)."""

    def per_row(self, actions: Tensor, cand: Tensor) -> Tensor:
        """What each row follows: here its candidate's actions (H, b, A)."""
        return actions.transpose(0, 1).index_select(1, cand)

    def action(self, t: int, per_row: Tensor, obs: Tensor) -> Tensor:
        """The rows' actions (b, A) at step ``t`` and observations ``obs``."""
        return per_row[t]


class FeedbackGains(OpenLoop):
    """Candidates are gains (N, rows, act_dim) of the feedback law, each row's action computed from its own state."""

    searches_actions = False
    section = FeedbackConfig
    check_config = staticmethod(check_feedback)

    @staticmethod
    def make_law(planner: Any, spec: EnvSpec, device: torch.device) -> LinearFeedback:
        f = planner.feedback
        return LinearFeedback(
            spec.obs_dim,
            spec.action_low,
            spec.action_high,
            horizon=planner.horizon,
            features=None if f.features is None else list(f.features),
            scale=None if f.scale is None else list(f.scale),
            bias=f.bias,
            device=device,
        )

    def __init__(self, law: LinearFeedback) -> None:
        self.law = law

    def horizon(self, actions: Tensor) -> int:
        return self.law.horizon

    def check(self, actions: Tensor) -> None:
        if tuple(actions.shape[1:]) != self.law.shape:
            raise ValueError(
                f"feedback candidates must be gains of shape (N, {self.law.shape[0]}, {self.law.shape[1]}), "
                f"got {tuple(actions.shape)}"
            )

    def per_row(self, actions: Tensor, cand: Tensor) -> Tensor:
        return actions.index_select(0, cand)  # (b, rows, A)

    def action(self, t: int, per_row: Tensor, obs: Tensor) -> Tensor:
        return self.law.actions(per_row, obs)


#: ``planner.candidates``: each kind's strategy class.
CANDIDATE_TABLE: dict[str, type[OpenLoop]] = {"open_loop": OpenLoop, "feedback": FeedbackGains}


def register_candidates(name: str, kind: type[OpenLoop]) -> type[OpenLoop]:
    """Add ``kind`` to :data:`CANDIDATE_TABLE` under ``name`` (a ``planner.candidates`` value from then on, from a
    module in the config key ``imports`` too; its ``section``, if any, is ``planner.<name>.*``); returns it.
    ValueError (one line) for a name that is not an identifier, one another kind holds, or a class that is not an
    :class:`OpenLoop` (or a subclass) whose ``section`` is None or a dataclass."""
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"a candidate kind's name must be an identifier (a config key), got {name!r}")
    if not (isinstance(kind, type) and issubclass(kind, OpenLoop)):
        raise ValueError(f"candidate kind {name!r} must be a subclass of particles.OpenLoop, got {kind!r}")
    if kind.section is not None and not is_dataclass(kind.section):
        raise ValueError(f"candidate kind {name!r}: its section must be a dataclass or None, got {kind.section!r}")
    taken = CANDIDATE_TABLE.get(name)
    if taken is not None and definition(taken) != definition(kind):  # the same class again: a module re-imported
        raise ValueError(f"candidate kind {name!r} is taken ({taken.__qualname__}); give yours another name")
    CANDIDATE_TABLE[name] = kind
    return kind


def unknown_candidates(planner: Any) -> str | None:
    """What is wrong (from "its candidate kind") where a stored ``planner`` section (a run's config.yaml) names a
    candidate kind the table lacks; None where it names none (no ``candidates``: ``open_loop``)."""
    kind = str(planner.get("candidates", "open_loop"))
    if kind in CANDIDATE_TABLE:
        return None
    return (
        f"its candidate kind {kind!r} is not a kind here (a kind of your own is known where the module that calls "
        "register_candidates is imported: name that module in the config key imports, e.g. imports=[my_kind]; in a "
        "run's config.yaml: imports: [my_kind]; docs/api.md)"
    )
