"""The whole arm's fit: the joints one by one in `JOINT_ORDER` (`fit_arm`), the wrist's weight
shared between C and D, the command step and the per-segment delay offsets (`tune_offsets`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from protocol.alpha5 import JOINT_LETTERS
from reach_sim_bridge.fit.joint_fit import FitResult, coarse_start, default_refs, fit_joint
from reach_sim_bridge.fit.replay import VELOCITY_WEIGHT_S, ParamRef, Replay, params_with
from reach_sim_bridge.fit.segments import Segment, segment_delays
from reach_sim_bridge.model.params import ArmParams

WRIST_LOAD: ParamRef = ("link_mass_kg", JOINT_LETTERS.index("B"))
"""The wrist link's mass: most of C's load, and part of D's."""
WEAK_RATIO = 0.8
"""`fit_arm` takes C for a weak drive (its torque scale the ratio) when D carries the wrist at
less than this share of the weight C's fit gave it (the envelope's heaviest and lightest
wrists differ by 2.6x in net weight, a drive at 25 % torque by 4x)."""


def wrist_weight(params: ArmParams, mass: float | None = None) -> float:
    """The wrist link's net weight in water (kg), with `mass` in place of its own."""
    b = WRIST_LOAD[1]
    m = params.link_mass_kg[b] if mass is None else mass
    return m - params.link_volume_l[b] * 1e-3 * params.water_density


JOINT_ORDER = ("E", "B", "C", "D")
"""Fitting order: E and B carry no gravity load; C's load (the wrist link) is fitted before
D, whose load includes it."""


OFFSET_SPAN_S = 0.01
"""`tune_offsets` searches +-this (s) around zero when the timestamps measured the delays ..."""
OFFSET_STEP_S = 0.001
"""... on this grid, then refines twice by half a step (to 0.25 ms)."""
CONSTANT_DELAY_MAX_S = 0.03
"""... and 0 .. this when they did not (the whole delay is then one constant)."""
QUANTA_S = (0.002, 0.0)
"""The arm's command steps `fit_arm` chooses between: the virtual arm steps its physics (and
takes commands) every 2 ms; a real arm's current loop is fast enough to count as 0."""


def tune_offsets(
    replay: Replay,
    params: ArmParams,
    segments: Sequence[Segment],
    velocity_weight: float = VELOCITY_WEIGHT_S,
) -> list[Segment]:
    """Each segment with the delay offset (a nuisance, one per segment) that fits it best on
    `params`, by a grid search then two half-step refinements: with commands taken on the arm's
    step grid the residual is piecewise constant in the offset (no gradient to follow), and
    the offset left by the timestamps' clock mapping differs from run to run by a fraction of
    a millisecond (the least transit seen in that run)."""
    out = []
    for seg in segments:
        if seg.link_delay_s is not None:
            grid = np.arange(-OFFSET_SPAN_S, OFFSET_SPAN_S + 1e-12, OFFSET_STEP_S)
        else:
            grid = np.arange(0.0, CONSTANT_DELAY_MAX_S + 1e-12, OFFSET_STEP_S)

        def cost(offset: float, seg: Segment = seg) -> float:
            r = replay.residuals(
                params, 0.0, [replace(seg, offset_s=float(offset))], velocity_weight
            )
            return float(r @ r)

        costs = [cost(o) for o in grid]
        best_cost, best = min(zip(costs, grid.tolist(), strict=True))
        step = float(grid[1] - grid[0]) if grid.size > 1 else OFFSET_STEP_S
        for _ in range(2):  # refine: half a step either side, twice
            step /= 2
            for o in (best - step, best + step):
                c = cost(o)
                if c < best_cost:
                    best_cost, best = c, o
        candidates = [(best_cost, best)]
        out.append(replace(seg, offset_s=min(candidates)[1]))
    return out


@dataclass(frozen=True)
class ArmFit:
    """`fit_arm`'s result: the arm, each joint's fit, the segments with their delay offsets,
    the command step chosen, and the median delay the replay used."""

    params: ArmParams
    results: dict[int, FitResult]
    segments: tuple[Segment, ...]  # the fitting segments, offsets tuned on the fitted arm
    quantum_s: float
    delay_s: float  # median over every command of every fitting segment


def fit_arm(
    replay: Replay,
    segments: Sequence[Segment],
    start: ArmParams | None = None,
    max_iter: int = 12,
    on_joint: Callable[[int, FitResult], None] | None = None,
    on_iteration: Callable[[int, int, float], None] | None = None,
    quanta: Sequence[float] = QUANTA_S,
    fit_starts: bool = True,
) -> ArmFit:
    """Fit every joint that has "fit" segments, in `JOINT_ORDER`, each from the arm found so
    far, with the delay held out of the physical fit (it trades off against the armature):

    1. Levenberg-Marquardt over the joint's physical parameters with the delays fixed at what
       the driver's timestamps measured per command (`link_delays`; offsets zero);
    2. each segment's delay offset is tuned on the fitted joint (`tune_offsets`) and the fit
       polished from there.

    With `fit_starts` the polish fits each window's starting state too (`fit_joint`).

    On the first joint the arm's command step is chosen among `quanta` (the one whose
    re-tuned median window error is smallest; a fresh fit if it is not the first tried)."""
    params = start if start is not None else ArmParams()
    results: dict[int, FitResult] = {}
    by_joint: dict[int, list[Segment]] = {}
    wrist_c: float | None = None  # the wrist link's mass as C's fit saw it
    quanta = tuple(quanta) or (replay.quantum_s,)
    replay.quantum_s = float(quanta[0])
    first = True
    for letter in JOINT_ORDER:
        j = JOINT_LETTERS.index(letter)
        segs = [s for s in segments if s.joint == j and s.role == "fit"]
        if not segs:
            continue

        def note(it: int, cost: float, j: int = j) -> None:
            if on_iteration is not None:
                on_iteration(j, it, cost)

        def one(
            base: ArmParams,
            segs: list[Segment] = segs,
            j: int = j,
            refs: list[ParamRef] | None = None,
            coarse: bool = True,
        ) -> tuple[FitResult, list[Segment]]:
            refs = refs or default_refs(j, fit_delay=False)
            # Offsets start at zero (the timestamps' word): tuned on an arm still far from
            # this one they would soak up its errors, the very trade-off they are to avoid.
            ready = [replace(x, offset_s=0.0) for x in segs]
            if coarse:
                base = coarse_start(replay, ready, base, refs)
            result = fit_joint(
                replay,
                ready,
                base,
                0.0,
                refs,
                max_iter=max_iter,
                on_iteration=note,
                # window starts only in the polish: fitted beside an arm still far from this
                # one they soak up its errors as the offsets would (and mislead the offsets)
                fit_starts=False,
            )
            ready = tune_offsets(replay, result.params, ready)
            if fit_starts:
                ready = replay.with_starts(ready)
            weights = replay.window_weights(result.params, 0.0, ready)
            polished = fit_joint(
                replay,
                ready,
                result.params,
                0.0,
                refs,
                max_iter=max(3, max_iter // 2),
                on_iteration=note,
                weights=weights,
                fit_starts=fit_starts,
            )
            return replace(
                polished,
                iterations=result.iterations + polished.iterations,
                rollouts=result.rollouts + polished.rollouts,
                costs=result.costs + polished.costs,
            ), list(polished.segments)

        refs_j = default_refs(j, fit_delay=False)
        if letter == "D" and wrist_c is not None:
            refs_j.append(WRIST_LOAD)  # the wrist's weight as D carries it
        result, ready = one(params, refs=refs_j)
        if first and len(quanta) > 1:

            def plain_cost(p: ArmParams, segs: list[Segment]) -> float:
                # The median window, not the sum: on a loaded host a few stalled windows
                # replay badly under either step and would decide the choice.
                return replay.median_window_rms(p, 0.0, segs)

            best = (plain_cost(result.params, ready), replay.quantum_s, result, ready)
            for q in quanta[1:]:
                replay.quantum_s = float(q)
                trial = tune_offsets(replay, result.params, ready)
                if plain_cost(result.params, trial) < best[0]:
                    res_q, ready_q = one(params, refs=refs_j)
                    cost_q = plain_cost(res_q.params, ready_q)
                    if cost_q < best[0]:
                        best = (cost_q, float(q), res_q, ready_q)
            _, quantum, result, ready = best
            replay.quantum_s = quantum
        first = False
        params = result.params
        results[j] = result
        by_joint[j] = ready
        if letter == "C":
            wrist_c = params.link_mass_kg[WRIST_LOAD[1]]
        if letter == "D" and wrist_c is not None:
            # C's drive and the wrist's weight are one unknown to C's fit; D carries the
            # wrist without C's drive. A C that saw the wrist heavier than D does is weak.
            scale = wrist_weight(params) / max(wrist_weight(params, wrist_c), 1e-9)
            c = JOINT_LETTERS.index("C")
            if 0.0 < scale < WEAK_RATIO:
                refs_c = [*default_refs(c, fit_delay=False)[:3], ("torque_scale", c)]
                scaled = [v * scale for v in results[c].values[:3]]
                refit, ready_c = one(
                    params_with(params, refs_c, [*scaled, scale]),
                    [x for x in segments if x.joint == c and x.role == "fit"],
                    c,
                    refs_c,
                )
                params, results[c], by_joint[c] = refit.params, refit, ready_c
            else:  # C keeps the wrist it saw; D is fitted again with it
                held = params_with(params, [WRIST_LOAD], [wrist_c])
                result, ready = one(held, coarse=False)
                params, results[j], by_joint[j] = result.params, result, ready
        if on_joint is not None:
            on_joint(j, result)
    tuned = [x for j in sorted(by_joint) for x in by_joint[j]]
    delays = np.concatenate([segment_delays(s) for s in tuned]) if tuned else np.zeros(1)
    return ArmFit(params, results, tuple(tuned), replay.quantum_s, float(np.median(delays)))
