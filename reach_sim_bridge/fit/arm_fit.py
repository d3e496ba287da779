"""The whole arm's fit: the joints one by one in `JOINT_ORDER`, each at its full torque
(`fit_arm`), then the torque scales where something anchors them (`anchor_scales`: the
wrist's weight, which C and D both carry), the command step and the per-segment delay
offsets (`tune_offsets`)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from protocol.alpha5 import JOINT_LETTERS
from reach_sim_bridge.fit.identifiability import (
    DRAG,
    DRAG_SPEED,
    INERTIA,
    LOAD_RMS,
    Fisher,
    ScaleStatus,
    ScaleVerdict,
    joint_inertia,
    joint_load,
    load_exponents,
)
from reach_sim_bridge.fit.joint_fit import (
    LOAD,
    FitResult,
    buoyant_kg,
    coarse_start,
    default_refs,
    equivalent,
    fit_joint,
)
from reach_sim_bridge.fit.replay import (
    VELOCITY_WEIGHT_S,
    ParamRef,
    Replay,
    param_value,
    params_with,
    ref_name,
    schedule_key,
)
from reach_sim_bridge.fit.segments import Segment, segment_delays
from reach_sim_bridge.model.params import ArmParams
from reach_sim_bridge.model.twin import Combination, Estimate, Unidentified

WRIST_LOAD: ParamRef = ("link_mass_kg", JOINT_LETTERS.index("B"))
"""The wrist link's mass: most of C's load, and part of D's."""


def wrist_weight(params: ArmParams, mass: float | None = None) -> float:
    """The wrist link's net weight in water (kg), with `mass` in place of its own."""
    b = WRIST_LOAD[1]
    m = params.link_mass_kg[b] if mass is None else mass
    return m - params.link_volume_l[b] * 1e-3 * params.water_density


JOINT_ORDER = ("E", "B", "C", "D")
"""Fitting order: the first joint fitted chooses the command step (`fit_arm`); C and D are
compared once both are fitted (`anchor_scales`)."""


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
    return [
        replace(seg, offset_s=_best_offset(replay, params, seg, velocity_weight))
        for seg in segments
    ]


def _best_offset(replay: Replay, params: ArmParams, seg: Segment, velocity_weight: float) -> float:
    """`tune_offsets` on one segment: its best offset."""
    if seg.link_delay_s is not None:
        grid = np.arange(-OFFSET_SPAN_S, OFFSET_SPAN_S + 1e-12, OFFSET_STEP_S)
    else:
        grid = np.arange(0.0, CONSTANT_DELAY_MAX_S + 1e-12, OFFSET_STEP_S)
    # cost by schedule: on the arm's command step neighbouring offsets often land every
    # command alike, and so replay alike
    seen: dict[bytes, float] = {}

    def cost(offset: float, above: float) -> float:
        trial = [replace(seg, offset_s=float(offset))]
        key = schedule_key(replay.plan(trial[0], 0.0))
        if key not in seen or (seen[key] == math.inf and above == math.inf):
            # replayed only as far as it takes to see it cost more than `above`
            # (`Replay.cost`); the bounds only fall, so a point cut short stays cut short
            seen[key] = replay.cost(params, 0.0, trial, velocity_weight, above=above)
        return seen[key]

    # Each point bounded by the lowest cost before it: the costs kept, and so the choice (the
    # lowest, the smaller offset on a tie), are what the whole grid replayed in full gives.
    costs: list[float] = []
    for o in grid.tolist():
        costs.append(cost(o, min(costs, default=math.inf)))
    best_cost, best = min(zip(costs, grid.tolist(), strict=True))
    step = float(grid[1] - grid[0]) if grid.size > 1 else OFFSET_STEP_S
    for _ in range(2):  # refine: half a step either side, twice
        step /= 2
        for o in (best - step, best + step):
            c = cost(o, best_cost)
            if c < best_cost:
                best_cost, best = c, o
    return float(best)


@dataclass(frozen=True)
class ArmFit:
    """`fit_arm`'s result: the arm, each joint's fit, its torque scale's verdict, the segments
    with their delay offsets, the command step chosen, and the median delay the replay used."""

    params: ArmParams
    results: dict[int, FitResult]
    segments: tuple[Segment, ...]  # the fitting segments, offsets tuned on the fitted arm
    quantum_s: float
    delay_s: float  # median over every command of every fitting segment
    scales: dict[int, ScaleVerdict] = field(default_factory=dict)


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
    """Fit every joint that has "fit" segments, in `JOINT_ORDER`, each at its full torque
    (what the data fix is its parameters over its torque scale), with the delay held out of
    the physical fit (it trades off against the armature):

    1. Levenberg-Marquardt over the joint's physical parameters with the delays fixed at what
       the driver's timestamps measured per command (`link_delays`; offsets zero);
    2. each segment's delay offset is tuned on the fitted joint (`tune_offsets`) and the fit
       polished from there.

    With `fit_starts` the polish fits each window's starting state too (`fit_joint`). Then
    the torque scales (`anchor_scales`): C and D both weigh the wrist, each over its own
    scale, which ties their scales together; E's and B's nothing ties.

    On the first joint the arm's command step is chosen among `quanta` (the one whose
    re-tuned median window error is smallest; a fresh fit if it is not the first tried)."""
    params = start if start is not None else ArmParams()
    fitted = [
        JOINT_LETTERS.index(x)
        for x in JOINT_ORDER
        if any(s.joint == JOINT_LETTERS.index(x) and s.role == "fit" for s in segments)
    ]
    params = params_with(params, [("torque_scale", j) for j in fitted], [1.0] * len(fitted))
    results: dict[int, FitResult] = {}
    by_joint: dict[int, list[Segment]] = {}
    quanta = tuple(quanta) or (replay.quantum_s,)
    replay.quantum_s = float(quanta[0])

    # `one`'s fits before their polish, by what they depend on
    before_polish: dict[tuple[object, ...], FitResult] = {}

    def one(
        base: ArmParams, j: int, refs: list[ParamRef], coarse: bool = True
    ) -> tuple[FitResult, list[Segment]]:
        segs = [s for s in segments if s.joint == j and s.role == "fit"]
        scale = ("torque_scale", j)
        probe = [] if scale in refs else [scale]

        def note(it: int, cost: float) -> None:
            if on_iteration is not None:
                on_iteration(j, it, cost)

        # Offsets start at zero (the timestamps' word): tuned on an arm still far from
        # this one they would soak up its errors, the very trade-off they are to avoid.
        ready = [replace(x, offset_s=0.0) for x in segs]
        # What this stage does depends on the replay only through the segments' schedules
        # (from a coarse start, whose first replay resets the arm, not on what ran before):
        # asked again with the same ones it would do it again to the last bit. That is the
        # first joint's fit on another command step (below) when its schedules at offset 0
        # come out alike, or are the ones `Replay.plan` kept.
        key = (j, repr(base), tuple(refs), tuple(schedule_key(replay.plan(x, 0.0)) for x in ready))
        result = before_polish.get(key) if coarse else None
        if result is None:
            starts = [base]
            if coarse:
                # the wrist is D's load too, but D's grid leaves it (x3 the rollouts) to D's fit
                grid = [r for r in refs if not (r == WRIST_LOAD and j == D)]
                starts = coarse_start(replay, ready, base, refs, grid=grid)
            # from each start (`coarse_start`), the one that ends lower kept
            tried = [
                fit_joint(
                    replay,
                    ready,
                    start,
                    0.0,
                    refs,
                    max_iter=max_iter,
                    on_iteration=note,
                    # window starts only in the polish: fitted beside an arm still far from
                    # this one they soak up its errors as the offsets would (and mislead the
                    # offsets)
                    fit_starts=False,
                )
                for start in starts
            ]
            result = min(tried, key=lambda r: r.costs[-1])
            result = replace(
                result,
                iterations=sum(r.iterations for r in tried),
                rollouts=sum(r.rollouts for r in tried),
            )
            if coarse:
                before_polish[key] = result
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
            probe=probe,
        )
        return replace(
            polished,
            iterations=result.iterations + polished.iterations,
            rollouts=result.rollouts + polished.rollouts,
            costs=result.costs + polished.costs,
        ), list(polished.segments)

    def segs_of(j: int) -> list[Segment]:
        return [s for s in segments if s.joint == j and s.role == "fit"]

    weighed = {j for j in fitted if j not in (C, D) and payload_of(segs_of(j)) is not None}
    first = True
    for j in fitted:
        refs_j = default_refs(j, fit_delay=False)
        if j in weighed:
            # excited with and without a known load: its inertia, which does not scale with
            # the drive, weighs the scale (`weighed_scale`)
            refs_j.append(("torque_scale", j))
        base = params
        if j == D:
            # D weighs the wrist over its own scale, from the nominal wrist: whatever C's fit
            # found is C's drive as much as the wrist (`anchor_scales` compares the two)
            refs_j.append(WRIST_LOAD)
            base = params_with(params, [WRIST_LOAD], [ArmParams().link_mass_kg[WRIST_LOAD[1]]])
        result, ready = one(base, j, refs_j)
        if j == D and C in results:
            # How D's load splits between its link and the wrist has more than one basin
            # behind a large friction (6.4 N m: D weighed the wrist 18 % light, at a cost 45 %
            # above the true split's, and no step left it): D is fitted again from the wrist as
            # C weighed it, and the fit that replays D's motions better is kept.
            b = WRIST_LOAD[1]
            again = params_with(result.params, [WRIST_LOAD], [results[C].params.link_mass_kg[b]])
            other, other_ready = one(again, j, refs_j, coarse=False)
            if replay_cost(replay, other.params, segs_of(j)) < replay_cost(
                replay, result.params, segs_of(j)
            ):
                result, ready = other, other_ready
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
                    res_q, ready_q = one(base, j, refs_j)
                    cost_q = plain_cost(res_q.params, ready_q)
                    if cost_q < best[0]:
                        best = (cost_q, float(q), res_q, ready_q)
            _, quantum, result, ready = best
            replay.quantum_s = quantum
        first = False
        params = result.params
        results[j] = result
        by_joint[j] = ready
        if on_joint is not None and not (j == D and C in results):
            on_joint(j, result)
    scales: dict[int, ScaleVerdict] = {}
    if C in results and D in results:
        params, weak, scales = anchor_scales(params, results, lambda p, j, r: one(p, j, r, False))
        results[weak.joint], by_joint[weak.joint] = weak, list(weak.segments)
        if on_joint is not None:
            on_joint(D, results[D])
            if weak.joint == C:
                on_joint(C, weak)
    for j in fitted:
        if j in weighed:
            scales[j] = weighed_scale(j, results[j], segs_of(j))
        elif j not in scales:
            scales[j] = unanchored(j, results[j])
    tuned = [x for j in sorted(by_joint) for x in by_joint[j]]
    delays = np.concatenate([segment_delays(s) for s in tuned]) if tuned else np.zeros(1)
    return ArmFit(params, results, tuple(tuned), replay.quantum_s, float(np.median(delays)), scales)


DAMPING_SHARE = 0.1
"""Viscous damping whose torque at `DRAG_SPEED` is under this share of the joint's Coulomb
friction is reported unidentifiable: the motions barely depend on it, and model errors the
sigma does not count go into it (a C behind 5.9 N m of friction came out 15 % off at a 2.6 %
sigma; behind 6.6 N m, -91 % to +211 %)."""


def replay_cost(replay: Replay, params: ArmParams, segments: Sequence[Segment]) -> float:
    """`segments`' squared residual on `params`, the delay offsets tuned to it and the windows
    started from the readings: to compare fits that weighted and started them each its own
    way."""
    r = replay.residuals(params, 0.0, tune_offsets(replay, params, segments))
    return float(r @ r)


IDENTIFIED_SIGMA = 0.03
"""A torque scale the data give to within this (relative, 1 sigma) is reported as identified,
a looser one as unidentifiable beside what is known; and the same bar for each value of a joint
whose scale was fitted (its value is its combination over the scale times the scale, so the
scale's sigma adds), a looser one reported as that combination. Tight because the Fisher
information's sigma understates (the residuals are correlated in time): D at 25 % torque behind
2.65x sensor noise had its armature 11.4 % low at a stated 3.5 %."""

C = JOINT_LETTERS.index("C")
D = JOINT_LETTERS.index("D")
D_LOAD: ParamRef = ("link_mass_kg", D)
"""The link D moves: D's own load beside the wrist's."""


def anchor_scales(
    params: ArmParams,
    results: dict[int, FitResult],
    refit: Callable[[ArmParams, int, list[ParamRef]], tuple[FitResult, list[Segment]]],
) -> tuple[ArmParams, FitResult, dict[int, ScaleVerdict]]:
    """C's and D's torque scales from the wrist both weigh: each fit at full torque found the
    wrist's net weight over its own scale, so D's over C's is C's scale over D's. The stronger
    drive is taken at its datasheet torque per amp (the anchor: a worn drive is one joint's);
    the weaker is fitted again with its torque scale free and the wrist held at what the
    stronger weighed (an absolute load in N m), from its fit scaled to the ratio
    (`equivalent`). Where the two weights do not tell which drive is the weaker (the ratio
    within two of its sigmas of 1, and that sigma over `IDENTIFIED_SIGMA`) neither scale is
    known: a D at 70 % torque, weighed on two short relays at 1x sensor noise, once looked
    the stronger. Returns the arm, the weaker joint's new fit and both verdicts."""
    b = WRIST_LOAD[1]
    w_c = wrist_weight(results[C].params)
    w_d = wrist_weight(results[D].params)
    ratio = w_d / max(w_c, 1e-9)  # s_C / s_D
    # each weight as its own fit saw it, that fit's scale taken as known
    sigma_ratio = math.hypot(
        _net_sigma(results[C], WRIST_LOAD, given=[("torque_scale", C)]),
        _net_sigma(results[D], WRIST_LOAD, given=[("torque_scale", D)]),
    )
    told = abs(math.log(ratio)) > 2 * sigma_ratio or sigma_ratio <= IDENTIFIED_SIGMA
    weak, strong = (D, C) if ratio >= 1.0 else (C, D)
    held = params_with(params, [WRIST_LOAD], [results[strong].params.link_mass_kg[b]])
    loads = [D_LOAD] if weak == D else []
    base = equivalent(held, weak, min(ratio, 1.0 / ratio), loads)
    refs = [*default_refs(weak, fit_delay=False)[:3], *loads, ("torque_scale", weak)]
    result, _ = refit(base, weak, refs)
    letters = JOINT_LETTERS[strong], JOINT_LETTERS[weak]
    weighed = (
        f"at full torque {letters[0]} weighs the wrist at "
        f"{wrist_weight(results[strong].params):.3f} kg, {letters[1]} at "
        f"{wrist_weight(results[weak].params):.3f} kg, their ratio to "
        f"+-{100 * sigma_ratio:.1f} %"
    )
    if told:
        anchor = ScaleVerdict(
            strong,
            ScaleStatus.ANCHOR,
            1.0,
            None,
            f"the stronger of C and D ({weighed}): taken at its datasheet torque per amp "
            "(an assumption: a worn drive is one joint's)",
        )
    else:
        anchor = ScaleVerdict(
            strong,
            ScaleStatus.UNIDENTIFIABLE,
            1.0,
            sigma_ratio,
            f"which of C and D is the weaker cannot be told ({weighed}); the twin takes "
            f"{letters[0]}'s datasheet torque (1)",
        )
    fisher = result.fisher
    scale_ref = ("torque_scale", weak)
    own = fisher.sigma({scale_ref: 1.0}) if fisher is not None else math.inf
    wrist = _net_sigma(results[strong], WRIST_LOAD, given=[("torque_scale", strong)])
    sigma = math.hypot(own, wrist) if told else max(math.hypot(own, wrist), sigma_ratio)
    value = result.params.torque_scale[weak]
    found = told and sigma <= IDENTIFIED_SIGMA
    verdict = ScaleVerdict(
        weak,
        ScaleStatus.IDENTIFIED if found else ScaleStatus.UNIDENTIFIABLE,
        value,
        sigma,
        f"fitted against the wrist's weight as {letters[0]} weighed it ({weighed})"
        + ("" if found else f"; to +-{100 * sigma:.0f} % only"),
    )
    return result.params, result, {strong: anchor, weak: verdict}


def payload_of(segments: Sequence[Segment]) -> tuple[float, float] | None:
    """The known load (kg, litres) of a joint's segments if some were logged holding it and
    some without (the two a torque scale can be weighed between); None otherwise."""
    loads = {(s.payload_kg, s.payload_volume_l) for s in segments}
    held = sorted(x for x in loads if x[0] > 0.0)
    return held[-1] if held and (0.0, 0.0) in loads else None


def weighed_scale(joint: int, result: FitResult, segments: Sequence[Segment]) -> ScaleVerdict:
    """The verdict on a torque scale fitted from motions with and without a known load in the
    jaws: the load's inertia in kg m^2 does not scale with the drive, so the drive's torque
    per amp is the one that moves both as logged. Identified where the data give it to
    `IDENTIFIED_SIGMA`; the twin keeps the fitted value either way."""
    load = payload_of(segments)
    kg = load[0] if load is not None else 0.0
    scale_ref = ("torque_scale", joint)
    fisher = result.fisher
    sigma = fisher.sigma({scale_ref: 1.0}) if fisher is not None else math.inf
    value = result.params.torque_scale[joint]
    found = sigma <= IDENTIFIED_SIGMA
    return ScaleVerdict(
        joint,
        ScaleStatus.IDENTIFIED if found else ScaleStatus.UNIDENTIFIABLE,
        value,
        sigma,
        f"fitted against the inertia of a known {kg:g} kg load in the jaws (motions with "
        "and without it)" + ("" if found else f"; to +-{100 * sigma:.0f} % only"),
    )


def unanchored(joint: int, result: FitResult) -> ScaleVerdict:
    """The verdict on a torque scale nothing anchors: E and B carry no load worth the name,
    and C or D without the other has nothing to weigh the wrist against. The twin takes the
    datasheet torque; the sigma is what the Fisher information gives from the little that does
    not scale (the links' own inertia, B's small load), which the fit does not lean on."""
    letter = JOINT_LETTERS[joint]
    scale_ref = ("torque_scale", joint)
    fisher = result.fisher
    sigma = (
        fisher.sigma({scale_ref: 1.0}) if fisher is not None and scale_ref in fisher.refs else None
    )
    if letter == "E":
        why = (
            "E turns about the vertical: no load weighs its torque against a known one (a "
            "known load in the jaws would, E's motions logged with and without it: "
            "identify.py --payload)"
        )
    elif letter == "B":
        why = (
            "B's only load is the wrist's weight a few millimetres off its roll axis (mN m, "
            "a model assumption): too small to weigh its torque against"
        )
    else:
        other = "D" if letter == "C" else "C"
        why = f"{other} was not identified: nothing weighs the wrist at a known torque"
    return ScaleVerdict(
        joint,
        ScaleStatus.UNIDENTIFIABLE,
        result.params.torque_scale[joint],
        sigma,
        why + "; the twin takes its datasheet torque (1)",
    )


def _net_sigma(result: FitResult, load: ParamRef, given: Sequence[ParamRef] = ()) -> float:
    """Relative 1-sigma of a fitted load's net weight (its effective mass's, times m / net),
    with the parameters `given` known (the anchor's own torque scale)."""
    fisher = result.fisher
    if fisher is None or load not in fisher.refs:
        return math.inf
    m = result.params.link_mass_kg[load[1]]
    net = m - buoyant_kg(result.params, load[1])
    return fisher.sigma({load: 1.0}, given) * m / max(net, 1e-9)


def parameter_verdicts(fit: ArmFit) -> tuple[dict[str, Estimate], dict[str, Unidentified]]:
    """What the fit can report, per parameter name: the identified ones with their 1-sigma,
    and for the rest the twin's value and the combination known. A joint whose torque scale
    is unidentifiable has its armature, damping and Coulomb friction known only over that
    scale (the armature with the links' inertia: `INERTIA`). A load (an effective link mass)
    is never known by itself: mass and displaced volume act together, and how the weight
    splits between D's link and the wrist rests on the C link's datasheet weight; what the
    data fix is the joint's load (`LOAD_RMS`), over its scale where that is unidentifiable."""
    known: dict[str, Estimate] = {}
    unknown: dict[str, Unidentified] = {}
    for j, result in sorted(fit.results.items()):
        verdict = fit.scales.get(j)
        scale_ref: ParamRef = ("torque_scale", j)
        free = verdict is not None and verdict.status is ScaleStatus.UNIDENTIFIABLE
        s_twin = verdict.value if verdict is not None and free else 1.0
        # an anchored scale is known (the anchor's assumption); a fitted one is estimated
        given = [] if free or scale_ref in result.refs else [scale_ref]
        fisher = result.fisher
        s_name = ref_name(scale_ref)
        letter = JOINT_LETTERS[j]
        over = f"/{s_name}" if free else ""
        #: the scale this joint's values were fitted with (0: anchored or unidentifiable)
        fitted_scale = (
            verdict.value
            if verdict is not None and verdict.status is ScaleStatus.IDENTIFIED
            else 0.0
        )
        if verdict is not None and verdict.status is ScaleStatus.IDENTIFIED:
            known[s_name] = Estimate(verdict.value, (verdict.sigma or 0.0) * verdict.value)
        elif verdict is not None and free:
            unknown[s_name] = Unidentified(verdict.value, verdict.reason)
        loads = [r for r in result.refs if r[0] == LOAD]
        if loads:
            value = joint_load(result.params, j)
            exps = load_exponents(result.params, j, loads)
            if free:
                exps[scale_ref] = -1.0
            combo = Combination(
                f"{LOAD_RMS}[{letter}]{over}",
                value / s_twin,
                _rel(fisher, exps, given) * value / s_twin,
            )
            for ref in loads:
                unknown[ref_name(ref)] = Unidentified(
                    param_value(result.params, 0.0, ref),
                    f"an effective mass: mass and displaced volume act together, and what "
                    f"{letter} carries is known as a whole",
                    combo,
                )
        friction = result.params.frictionloss[j]
        for ref, value, sigma in zip(result.refs, result.values, result.sigma, strict=True):
            if ref == scale_ref or ref[0] == LOAD:
                continue
            name = ref_name(ref)
            exps = {ref: 1.0, **({scale_ref: -1.0} if free else {})}
            if ref[0] == "damping" and value * DRAG_SPEED < DAMPING_SHARE * friction:
                drag = friction + value * DRAG_SPEED
                f_ref: ParamRef = ("frictionloss", j)
                exps = {f_ref: friction / drag, ref: value * DRAG_SPEED / drag}
                if free:
                    exps[scale_ref] = -1.0
                unknown[name] = Unidentified(
                    value,
                    f"behind Coulomb friction: its torque at {DRAG_SPEED:g} rad/s is under "
                    f"{DAMPING_SHARE:.0%} of the friction: what the fit gets wrong goes into it",
                    Combination(
                        f"{DRAG}[{letter}]{over}",
                        drag / s_twin,
                        _rel(fisher, exps, given) * drag / s_twin,
                    ),
                )
            elif free and ref[0] == "armature":
                total = joint_inertia(result.params, j)
                exps[ref] = value / total  # d log(total) = armature / total d log(armature)
                unknown[name] = Unidentified(
                    value,
                    f"known only with the links' inertia, over {s_name} (unidentifiable)",
                    Combination(
                        f"{INERTIA}[{letter}]{over}",
                        total / s_twin,
                        _rel(fisher, exps) * total / s_twin,
                    ),
                )
            elif free:
                unknown[name] = Unidentified(
                    value,
                    f"known only over {s_name} (unidentifiable)",
                    Combination(f"{name}{over}", value / s_twin, _rel(fisher, exps) * value),
                )
            elif fitted_scale and sigma > IDENTIFIED_SIGMA * abs(value):
                unknown[name] = _over_fitted_scale(result, j, ref, value, sigma, fitted_scale)
            else:
                known[name] = Estimate(value, sigma)
    return known, unknown


def _over_fitted_scale(
    result: FitResult, j: int, ref: ParamRef, value: float, sigma: float, scale: float
) -> Unidentified:
    """A value of joint `j`, whose scale was fitted, that the data do not give to
    `IDENTIFIED_SIGMA`: reported as what they do fix, the value over the scale (the armature
    with the links' inertia), with its own sigma."""
    scale_ref: ParamRef = ("torque_scale", j)
    s_name = ref_name(scale_ref)
    letter = JOINT_LETTERS[j]
    name = ref_name(ref)
    exps = {ref: 1.0, scale_ref: -1.0}
    combo_name, combo_value = f"{name}/{s_name}", value / scale
    if ref[0] == "armature":
        total = joint_inertia(result.params, j)
        exps[ref] = value / total
        combo_name, combo_value = f"{INERTIA}[{letter}]/{s_name}", total / scale
    return Unidentified(
        value,
        f"{sigma / abs(value):.1%} at 1 sigma, looser than {IDENTIFIED_SIGMA:.0%}: known "
        f"over {s_name}, which was fitted",
        Combination(combo_name, combo_value, _rel(result.fisher, exps) * combo_value),
    )


def _rel(
    fisher: Fisher | None, exps: dict[ParamRef, float], given: Sequence[ParamRef] = ()
) -> float:
    """Relative 1-sigma of a product of parameters (inf without the information)."""
    if fisher is None or any(r not in fisher.refs for r in exps):
        return math.inf
    return fisher.sigma(exps, [g for g in given if g in fisher.refs])
