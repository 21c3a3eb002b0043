"""What a study runs, as one unit (:class:`Design`): its registered jobs in their registered order (seed-major, or
each job a sweep of every arm of one seed, so a study cut short is still paired), the commit its runs are made from,
and which jobs its committed rows do not hold yet. A study declares its design in its own module as ``DESIGN``,
beside its ``PUBLICATION``; the one table of designs is :data:`pets.experiments.published.DESIGNS`, from which
``docs/scripts/study_jobs.py`` makes the background queues of a machine (which core runs what is that script's
choice, not the design's) and ``pets.compare design`` prints the commands.
"""

from __future__ import annotations

import shlex
from collections.abc import Callable, Sequence
from collections.abc import Set as AbstractSet
from dataclasses import dataclass
from pathlib import Path

#: A job's kinds: ``run_pets.py ARGS`` (one run; its directory is the job's) or ``python -m pets.compare ARGS`` (a
#: sweep; the job's directory holds its log only).
KINDS = ("pets", "compare")


@dataclass(frozen=True)
class Job:
    """One registered job. ``name``: its directory's, unique in the study; ``seed``: the model seed it runs (the
    pairing unit); ``folder``: the study's folder of directories (under a machine's runs folder); ``args``: the
    command's arguments, where ``{out}`` stands for that folder (a sweep's ``--out``)."""

    name: str
    seed: int
    folder: str
    kind: str
    args: tuple[str, ...]

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"Job {self.name!r}: kind must be one of {', '.join(KINDS)}, got {self.kind!r}")

    def command(self, runs: Path) -> str:
        """The command as a queue line holds it (``docs/scripts/run_queue.sh``: a ``pets`` job's arguments, a
        ``compare`` job's whole line), ``{out}`` resolved under ``runs``."""
        args = shlex.join(a.replace("{out}", str(runs / self.folder)) for a in self.args)
        return args if self.kind == "pets" else f"python -m pets.compare {args}"

    def shell_line(self, runs: Path) -> str:
        """The whole command to type in a worktree at the study's commit; a run's ``--out`` is its directory."""
        if self.kind == "pets":
            return f"python run_pets.py {self.command(runs)} --out {shlex.quote(str(runs / self.folder / self.name))}"
        return self.command(runs)


@dataclass(frozen=True)
class Design:
    """One study's registered work. ``commit``: the commit every run of the study is made from (a worktree pinned
    there: a refactor never changes code under a running study); ``jobs(tree)``: every registered job, in the
    registered order, under a repository tree (a design may depend on committed results, e.g. the envs where a
    gate passed); ``done(tree)``: the names of the jobs the committed rows under ``tree`` complete; ``rule``: how
    ``done`` counts a job where that is not simply its own rows (said beside the counts)."""

    name: str
    issue: int
    commit: str
    jobs: Callable[[Path], Sequence[Job]]
    done: Callable[[Path], AbstractSet[str]]
    rule: str = ""

    def left(self, tree: Path) -> list[Job]:
        """The jobs the committed rows under ``tree`` do not complete, in the registered order."""
        return self._state(tree)[1]

    def _state(self, tree: Path) -> tuple[list[Job], list[Job]]:
        """Every registered job, and those left."""
        jobs, done = list(self.jobs(tree)), self.done(tree)
        return jobs, [job for job in jobs if job.name not in done]

    def progress(self, tree: Path) -> str:
        """A study's progress block: how many registered jobs the committed rows under ``tree`` complete, and which
        are left, in their order (generated: a study page never types these counts)."""
        jobs, left = self._state(tree)
        rest = ", ".join(f"`{job.name}`" for job in left) if left else "none"
        rule = f" ({self.rule})" if self.rule else ""
        done = f"**{len(jobs) - len(left)} of {len(jobs)}**{rule}"
        return (f"Registered jobs complete in the committed rows: {done}, run from commit `{self.commit}` (`python -m "
                f"pets.compare design {self.name} --left` prints the commands of the rest). Left, in the registered "
                f"order: {rest}.")  # fmt: skip

    def listing(self, tree: Path, runs: Path, left_only: bool = False) -> str:
        """The design as shell lines under a comment line: every job (or those left), ``runs`` their folder."""
        jobs, left = self._state(tree)
        head = (f"# {self.name} (issue {self.issue}): {len(jobs)} registered jobs, {len(left)} not complete in the "
                f"committed rows; from a worktree at {self.commit}: git worktree add --detach ../wt-{self.name} "
                f"{self.commit}")  # fmt: skip
        return "\n".join([head, *(job.shell_line(runs) for job in (left if left_only else jobs))])
