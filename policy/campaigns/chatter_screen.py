"""Controllers screened for chatter offline (`tools/screen_chatter.py`, docs/chatter.md): the
driver's chatter guard (reach_driver/chatter.py) replayed over direct-backend episodes, checked
against an independent definition.

Each episode runs on the direct backend (`policy.campaigns.evaluation`, degraded arms with
--perturb, noisy readings with --noise) and its trace, at the control rate, is replayed through the
same `ChatterDetector` the control loop runs: step k gives it the state at sample k and the command
computed from it (the current held over the period ending at sample k+1). It is replayed twice:
on the simulator's true angles (what the driver sees from the virtual arm) and on readings
with the sensor noise of `SensorNoise` added (a noisier arm).

Independently of the detector, an episode *chatters* when its joints spend more than
`--late-energy` J (default 1) of mechanical energy over the last `--late-window` s (default 10)
of the episode: every step has arrived long before then (settling <= 5 s here), so a
controller at rest spends ~0.01 J there and a limit cycle ~30 J (docs/chatter.md).
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from policy.campaigns.evaluation import (
    RunConfig,
    evaluate,
    load_controller,
    parse_controller_params,
    random_episodes,
)
from policy.tasks.episodes import EpisodeResult
from protocol.alpha5 import DEFAULT_CURRENT_LIMITS_MA
from reach_driver.chatter import ChatterConfig, ChatterDetector, Verdict
from reach_sim_bridge.model.sensors import SensorNoise

CHUNK = 40
LATE_ENERGY_J = 1.0
LATE_WINDOW_S = 10.0
NOISE_STREAM = 7
"""The noisy replay of episode seed s draws from default_rng([s, 7]), apart from the noise
the controller itself saw."""


@dataclass(frozen=True)
class Options:
    """The command line of `tools/screen_chatter.py` (its help says what each one does)."""

    out: Path
    controllers: str = "ddpg-distilled,ddpg-distilled-pure,pid"
    episodes: str = "640,200,200"
    param: Sequence[str] = ()
    seed: int = 20000
    perturb: float = 0.2
    noise: bool = True
    seconds: float = 20.0
    late_energy: float = LATE_ENERGY_J
    late_window: float = LATE_WINDOW_S
    workers: int = 1


def replay(
    result: EpisodeResult,
    config: ChatterConfig | None = None,
    limits_mA: Sequence[float] = DEFAULT_CURRENT_LIMITS_MA,
    noise: SensorNoise | None = None,
    rng: np.random.Generator | None = None,
) -> tuple[Verdict | None, float]:
    """The detector over one episode: its verdict (None if it never fired) and its longest
    cycle (s; up to the verdict when it fired)."""
    det = ChatterDetector(config or ChatterConfig(), limits_mA)
    trace = result.trace
    n = trace.q.shape[0] - 1
    for k in range(n):
        q, qdot = trace.q[k], trace.qdot[k]
        if noise is not None:
            q, qdot = noise.apply(q, qdot, rng or np.random.default_rng())
        verdict = det.update(k * trace.dt, q, qdot, result.currents_mA[k + 1], trace.target)
        if verdict is not None:
            return verdict, det.longest_s
    return None, det.longest_s


def late_energy(result: EpisodeResult, window_s: float = LATE_WINDOW_S) -> float:
    """Mechanical energy (J) over the last `window_s` of the episode (docs/metrics.md)."""
    trace = result.trace
    samples = int(round(window_s / trace.dt))
    power = trace.power
    if power is None:
        power = np.abs(trace.tau * trace.qdot)
    return float(np.sum(power[-samples:]) * trace.dt)


@dataclass(frozen=True)
class Row:
    controller: str
    index: int
    seed: int
    energy_j: float
    late_energy_j: float
    chattering: bool
    fired: bool
    fired_t: float | None
    delay_s: float | None  # from the joint first entering the band to the verdict
    verdict: str | None
    longest_s: float  # the longest cycle the detector saw (s)
    noisy_fired: bool
    noisy_longest_s: float


def screen_episode(name: str, index: int, seed: int, result: EpisodeResult, args: Options) -> Row:
    config = ChatterConfig()
    verdict, longest = replay(result, config)
    noisy, noisy_longest = replay(
        result, config, noise=SensorNoise(), rng=np.random.default_rng([seed, NOISE_STREAM])
    )
    late = late_energy(result, args.late_window)
    delay = None
    if verdict is not None:
        err = np.abs(result.trace.errors[:, verdict.joint])
        inside = np.flatnonzero(err < config.band_rad)
        delay = verdict.t - float(inside[0]) * result.trace.dt
    return Row(
        controller=name,
        index=index,
        seed=seed,
        energy_j=float(result.metrics.energy_j),
        late_energy_j=late,
        chattering=late > args.late_energy,
        fired=verdict is not None,
        fired_t=None if verdict is None else verdict.t,
        delay_s=delay,
        verdict=None if verdict is None else verdict.describe(),
        longest_s=longest,
        noisy_fired=noisy is not None,
        noisy_longest_s=noisy_longest,
    )


def screen_chunk(name: str, start: int, count: int, args: Options) -> list[Row]:
    """Episodes start..start+count-1 of `args.seed`'s set, as `tools/evaluate.py --random`
    numbers them (episode i: seed + i)."""
    episodes = random_episodes(start + count, args.seed)[start:]
    config = RunConfig(
        seconds=args.seconds,
        noise=SensorNoise() if args.noise else None,
        seed=args.seed + start,
        param_spread=args.perturb,
    )
    controller = load_controller(name, **parse_controller_params(args.param))
    evaluation = evaluate(controller, episodes, config, name=name)
    return [
        screen_episode(name, start + i, args.seed + start + i, r, args)
        for i, r in enumerate(evaluation.results)
    ]


def run_all(jobs: list[tuple[str, int, int]], args: Options) -> list[Row]:
    if args.workers <= 1:
        rows: list[Row] = []
        for name, start, count in jobs:
            rows.extend(screen_chunk(name, start, count, args))
            print(f"  {name} {start + count} episodes", file=sys.stderr, flush=True)
        return rows
    import ray

    ray.init(num_cpus=args.workers, include_dashboard=False, log_to_driver=False)
    try:
        remote = ray.remote(screen_chunk)
        pending = {remote.remote(name, s, c, args): (name, s, c) for name, s, c in jobs}
        rows = []
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            name, start, count = pending.pop(done[0])
            rows.extend(ray.get(done[0]))
            print(f"  {name} {start}..{start + count - 1} done", file=sys.stderr, flush=True)
        return sorted(rows, key=lambda r: (r.controller, r.index))
    finally:
        ray.shutdown()


def tally(rows: list[Row]) -> dict[str, Any]:
    chat = [r for r in rows if r.chattering]
    good = [r for r in rows if not r.chattering]
    return {
        "episodes": len(rows),
        "chattering": len(chat),
        "caught": sum(r.fired for r in chat),
        "missed": [r.index for r in chat if not r.fired],
        "good": len(good),
        "false_positives": [r.index for r in good if r.fired],
        "noisy_caught": sum(r.noisy_fired for r in chat),
        "noisy_false_positives": [r.index for r in good if r.noisy_fired],
        "good_longest_cycle_s": max((r.longest_s for r in good), default=0.0),
        "good_noisy_longest_cycle_s": max((r.noisy_longest_s for r in good), default=0.0),
        "good_longest_top": sorted(((round(r.longest_s, 2), r.index) for r in good), reverse=True)[
            :5
        ],
        "good_late_energy_max_j": max((r.late_energy_j for r in good), default=0.0),
        "chattering_late_energy_min_j": min((r.late_energy_j for r in chat), default=None),
        "delay_max_s": max((r.delay_s or 0.0 for r in chat if r.fired), default=None),
        "chattering_episodes": [r.index for r in chat],
    }


def execute(args: Options) -> int:
    """Screen, write the JSON and print the tallies; the exit code (2: a bad option)."""
    names = [n.strip() for n in args.controllers.split(",") if n.strip()]
    counts = [int(c) for c in args.episodes.split(",")]
    if len(counts) == 1:
        counts *= len(names)
    if len(counts) != len(names) or min(counts) < 1:
        print("error: --episodes needs one positive count or one per controller", file=sys.stderr)
        return 2
    try:
        params = parse_controller_params(args.param)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    jobs = [
        (name, start, min(CHUNK, n - start))
        for name, n in zip(names, counts, strict=True)
        for start in range(0, n, CHUNK)
    ]
    t0 = time.monotonic()
    rows = run_all(jobs, args)
    wall = time.monotonic() - t0
    report: dict[str, Any] = {
        "settings": {
            "controllers": names,
            "params": params,
            "episodes": counts,
            "seed": args.seed,
            "perturb": args.perturb,
            "noise": args.noise,
            "seconds": args.seconds,
            "late_energy_j": args.late_energy,
            "late_window_s": args.late_window,
            "workers": args.workers,
            "chatter_config": {k: str(v) for k, v in asdict(ChatterConfig()).items()},
        },
        "wall_seconds": wall,
        "by_controller": {n: tally([r for r in rows if r.controller == n]) for n in names},
        "total": tally(rows),
        "episodes": [asdict(r) for r in rows],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1), encoding="utf-8")
    for name, t in [*report["by_controller"].items(), ("total", report["total"])]:
        print(
            f"{name}: {t['episodes']} episodes, {t['chattering']} chattering "
            f"{t['chattering_episodes'] if name != 'total' else ''}, caught {t['caught']} "
            f"(noisy {t['noisy_caught']}); {t['good']} good, false positives "
            f"{len(t['false_positives'])} (noisy {len(t['noisy_false_positives'])}); "
            f"good longest cycle {t['good_longest_cycle_s']:.2f} s (noisy "
            f"{t['good_noisy_longest_cycle_s']:.2f} s) of {ChatterConfig().sustain_s:g} s; "
            f"late energy good <= {t['good_late_energy_max_j']:.3f} J, chattering >= "
            f"{t['chattering_late_energy_min_j']}"
        )
    print(f"{len(rows)} episodes in {wall:.0f} s with {args.workers} worker(s); wrote {args.out}")
    return 0
