#!/usr/bin/env python3
"""Speed-up of an evaluation campaign on Ray (policy/campaigns/parallel.py) over the serial runner.

The same episodes (seed 2020's, sensor noise, +-20 % degraded arms), serially with
`policy.campaigns.evaluation.evaluate` and on a local Ray with 2 workers, in this process; the
results must be identical. Ray's start-up and the workers' first imports are left out (a warm-up
campaign runs first): a campaign long enough to be worth parallelising amortises them. Best
of ``--repeats`` for each side, since other jobs may share the cores. Aim: >= 1.8x on 2 cores;
exits 1 if missed (and 2 if the results differ).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from policy.campaigns.evaluation import RunConfig, evaluate, load_controller, random_episodes
from policy.campaigns.parallel import evaluate_parallel, import_ray
from reach_sim_bridge.model.sensors import SensorNoise

AIM = 1.8
WORKERS = 2


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--controller", default="pid", help="controller name (default pid)")
    p.add_argument("--episodes", type=int, default=16, help="episodes (default 16)")
    p.add_argument("--seconds", type=float, default=20.0, help="episode length (default 20 s)")
    p.add_argument("--repeats", type=int, default=2, help="best of this many (default 2)")
    args = p.parse_args()
    ray = import_ray()
    episodes = random_episodes(args.episodes, 2020)
    config = RunConfig(seconds=args.seconds, noise=SensorNoise(), seed=2020, param_spread=0.2)
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    ray.init(num_cpus=WORKERS, include_dashboard=False, log_to_driver=False)
    startup = time.perf_counter() - t0
    try:
        evaluate_parallel(args.controller, {}, episodes[:WORKERS], config)  # warm-up
        serial_s, ray_s, share = [], [], []
        for _ in range(args.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            serial = evaluate(load_controller(args.controller), episodes, config)
            serial_s.append(time.perf_counter() - t0)
            share.append((time.process_time() - c0) / serial_s[-1])
            t0 = time.perf_counter()
            parallel = evaluate_parallel(args.controller, {}, episodes, config)
            ray_s.append(time.perf_counter() - t0)
    finally:
        ray.shutdown()
    same = all(
        a.metrics == b.metrics for a, b in zip(serial.results, parallel.results, strict=True)
    )
    speedup = min(serial_s) / min(ray_s)
    load_after = os.getloadavg()[0]
    print(
        f"campaign of {args.episodes} x {args.seconds:g} s {args.controller} episodes: "
        f"serial {min(serial_s):.2f} s, Ray with {WORKERS} workers {min(ray_s):.2f} s "
        f"(best of {args.repeats}; Ray start-up {startup:.1f} s, not counted) -> "
        f"{speedup:.2f}x (aim >= {AIM}x on {WORKERS} cores); results identical: {same}; "
        f"1-minute load average {load_before:.1f} before, {load_after:.1f} after "
        f"on {os.cpu_count()} cores (the serial run got {max(share):.0%} of a core; on shared "
        "cores the workers get less than one each, and the aim is for idle ones)"
    )
    if not same:
        return 2
    return 0 if speedup >= AIM else 1


if __name__ == "__main__":
    sys.exit(main())
