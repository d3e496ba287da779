"""Reselecting a run's actor from every checkpoint it kept, on more episodes than training's
checkpoint sets, by a rule fixed before any test episode is looked at.

A run keeps the checkpoint that scores best on its own small sets (20 standard episodes, 10 with
a weak joint, 40 envelope arms). Late in a run checkpoints differ less than those few episodes
can tell apart, so the kept actor is partly the luck of the draw. The trainer keeps every
checkpoint's actor (`CHECKPOINT_ACTORS`), and this module scores them all on a validation set
of its own (`VALIDATION`: seeds apart from the checkpoint sets', 10 000 plus offsets, and from
the ablation's test sets, 40 000 and 50 000) and picks one by `choose`:

    the largest share of validation episodes *good* (reached at rest, overshoot under 2 %:
    the issue's envelope item read per episode), the standard set's share plus the
    envelope's; ties to the most reached at rest, then the lower mean standard overshoot.

Only the selection changes: the actors are the run's own, trained as they were.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from policy.campaigns.ablation import SMALL_OVERSHOOT_PCT, HeldOutSets, cached_episodes
from policy.campaigns.parallel import run_on_ray
from policy.controllers.weights import CHECKPOINT_ACTORS, CheckpointActor

#: the validation set: as large as the ablation's test sets, on seeds of its own
VALIDATION = HeldOutSets(standard=40, envelope=100, seed=60_000)
#: what reselection writes into the run directory
RESELECTED = "reselected_actor.npz"
REPORT = "reselection.json"


@dataclass(frozen=True)
class CheckpointFigures:
    """One checkpoint's actor on the validation set (shares in [0, 1], means over episodes)."""

    env_steps: int
    path: str
    #: share of standard / envelope episodes reached at rest with overshoot under 2 %
    standard_good: float
    envelope_good: float
    standard_reached: float
    envelope_reached: float
    standard_overshoot_pct: float
    standard_msse: float
    standard_energy_j: float

    @property
    def merit(self) -> float:
        """What `choose` maximises: the two sets' shares of good episodes, added."""
        return self.standard_good + self.envelope_good


def _good(episode: dict[str, float]) -> bool:
    return bool(episode["reached"]) and episode["overshoot_pct"] < SMALL_OVERSHOOT_PCT


def _share(episodes: Sequence[dict[str, float]], pick: Callable[[dict[str, float]], bool]) -> float:
    """Share of `episodes` for which `pick` holds (0 for no episodes: an arm without an
    envelope set adds nothing)."""
    return float(np.mean([pick(e) for e in episodes])) if episodes else 0.0


def figures(
    env_steps: int, path: Path, episodes: dict[str, list[dict[str, float]]]
) -> CheckpointFigures:
    """A checkpoint's `CheckpointFigures` from its per-episode validation results."""
    standard, envelope = episodes["standard"], episodes["envelope"]
    return CheckpointFigures(
        env_steps=env_steps,
        path=str(path),
        standard_good=_share(standard, _good),
        envelope_good=_share(envelope, _good),
        standard_reached=_share(standard, lambda e: bool(e["reached"])),
        envelope_reached=_share(envelope, lambda e: bool(e["reached"])),
        standard_overshoot_pct=float(np.mean([e["overshoot_pct"] for e in standard])),
        standard_msse=float(np.mean([e["msse"] for e in standard])),
        standard_energy_j=float(np.mean([e["energy_j"] for e in standard])),
    )


def choose(rows: Sequence[CheckpointFigures]) -> CheckpointFigures:
    """The rule (module docstring): most good episodes, then (among actors with equally few)
    the most reached at rest, then the lower standard overshoot; an actor that never moves
    overshoots nothing, so reaching ranks first."""
    if not rows:
        raise ValueError("no checkpoint to choose from")
    return max(
        rows,
        key=lambda r: (
            r.merit,
            r.standard_reached + r.envelope_reached,
            -r.standard_overshoot_pct,
        ),
    )


def checkpoint_actors(
    run: Path, kind: CheckpointActor = CheckpointActor.KEPT
) -> list[tuple[int, Path]]:
    """A run's kept checkpoint actors of `kind`, by env steps."""
    folder = run / CHECKPOINT_ACTORS
    found = []
    for path in folder.glob(f"{kind.value}-*.npz"):
        steps = path.stem.removeprefix(f"{kind.value}-")
        if steps.isdigit():
            found.append((int(steps), path))
    if not found:
        raise FileNotFoundError(
            f"{run}: no {kind.value}-STEPS.npz in {CHECKPOINT_ACTORS}/ (runs keep every "
            "checkpoint's actor since this was added; older runs keep only best_actor.npz)"
        )
    return sorted(found)


@dataclass(frozen=True)
class Reselection:
    """Every checkpoint's figures and the one `choose` picked."""

    run: str
    kind: CheckpointActor
    sets: HeldOutSets
    rows: tuple[CheckpointFigures, ...]
    chosen: CheckpointFigures

    def to_dict(self) -> dict[str, object]:
        return {
            "run": self.run,
            "kind": self.kind.value,
            "sets": self.sets.to_dict(),
            "rule": "max standard_good + envelope_good, then standard_reached + "
            "envelope_reached, then min standard_overshoot_pct",
            "chosen": asdict(self.chosen),
            "rows": [asdict(r) for r in self.rows],
        }


@dataclass(frozen=True)
class ValidationJob:
    """One checkpoint actor to score, for a Ray worker."""

    path: str
    sets: HeldOutSets


def validation_job(job: ValidationJob) -> str:
    """Score one actor and keep its cache file; returns the actor's path."""
    path = Path(job.path)
    cached_episodes(path, job.sets, _cache(path))
    return job.path


def _cache(actor: Path) -> Path:
    return actor.with_suffix(".validation.json")


def reselect(
    run: Path,
    kind: CheckpointActor = CheckpointActor.KEPT,
    sets: HeldOutSets = VALIDATION,
    progress: Callable[[str], None] | None = None,
    workers: int | None = None,
    address: str | None = None,
) -> Reselection:
    """Score every kept checkpoint actor of `run` on `sets` (each cached beside its actor as
    ACTOR.validation.json) and choose one. With ``workers`` or ``address`` the actors are
    scored on Ray (`policy.campaigns.parallel`), one task each, with the same results."""
    actors = checkpoint_actors(run, kind)
    if workers is not None or address is not None:
        jobs = [ValidationJob(str(path), sets) for _, path in actors]
        tell = progress

        def scored(path: str) -> None:
            if tell is not None:
                tell(f"scored {Path(path).name}")

        run_on_ray(validation_job, jobs, workers, address, on_result=scored)
    rows = []
    for steps, path in actors:
        label = f"scoring {run.name} {path.name}"
        episodes = cached_episodes(path, sets, _cache(path), progress, label)
        rows.append(figures(steps, path, episodes))
    return Reselection(str(run), kind, sets, tuple(rows), choose(rows))


def write(reselection: Reselection) -> Path:
    """Copy the chosen actor to RUN/reselected_actor.npz (its .json beside it) and the report
    to RUN/reselection.json; returns the actor's path."""
    run = Path(reselection.run)
    chosen = Path(reselection.chosen.path)
    target = run / RESELECTED
    shutil.copyfile(chosen, target)
    sidecar = chosen.with_suffix(".json")
    if sidecar.is_file():
        shutil.copyfile(sidecar, target.with_suffix(".json"))
    (run / REPORT).write_text(json.dumps(reselection.to_dict(), indent=1), encoding="utf-8")
    return target
