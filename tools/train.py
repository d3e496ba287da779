"""Train an actor on ReachAlpha-v0 (DDPG, TD3, TD3 + behaviour cloning from the PD expert, as
the config says), with checkpoints that survive the session.

    .venv/bin/python tools/train.py --run runs/scratch-s0 --seed 0       # the shipped ddpg's recipe
    .venv/bin/python tools/train.py --run runs/scratch-s0 --resume       # continue later
    .venv/bin/python tools/train.py --config ours --run runs/ours-s0 --seed 0   # TD3+BC
    .venv/bin/python tools/train.py --config paper --run runs/paper-s0   # the paper's DDPG
    .venv/bin/python tools/train.py --arm bravo7 --run runs/bravo-s0     # on the Bravo 7

Writes to the run directory: config.json, train.csv (one row per finished episode: return and
losses), eval.jsonl (periodic deterministic evaluation), best_actor.npz/.json (best evaluated
actor with its provenance, the format policy/controllers/weights/ ships; with
`--set actor_average_tau=...` the averaged actor, and best_online_actor.npz/.json the online
one), checkpoint.pt + buffer.npz (everything to resume), commands.txt (every command given),
train.log (what was printed).

`--resume --set KEY=VALUE` applies the fields a resumed run can change (learning rates, batch
size, exploration, the BC schedule, evaluation cadence: `policy.rl.overrides.RESUMABLE`) and
refuses, naming the field and why, those it cannot (network sizes, the environment, the buffer,
the seed...).
Ctrl-C or SIGTERM saves a checkpoint, then exits 130 (143 for SIGTERM).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from protocol.extras import script_needs_extra
from protocol.models import ALPHA5, ArmModelName, model_named

with script_needs_extra("tools/train.py", "train"):
    from policy.campaigns.selection import envelope_results, envelope_summary
    from policy.controllers.weights import LEARNED_WEIGHTS
    from policy.rl.run_dir import COMMANDS, record_command, ship, start_run
    from policy.rl.scoring import evaluate_weights, params_arm_factory, weights_path
    from policy.rl.session import Sitting, train_run
    from reach_driver.controllers import load_controller
    from reach_driver.errors import DriverError


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--config",
        default="scratch",
        choices=["scratch", "paper", "paper-per-joint", "ours", "robust"],
        help="hyperparameter preset, a classmethod of policy.rl.config.DDPGConfig: scratch "
        "(the shipped ddpg, learned from scratch; default), paper (Carlucho et al. as "
        "stated, the reward on the norm of the error), paper-per-joint (its reward per "
        "joint), ours and robust (the distilled stack's stages: demonstrations and "
        "behaviour cloning from a privileged expert)",
    )
    p.add_argument(
        "--arm",
        choices=[m.value for m in ArmModelName],
        default=None,
        help="the arm to train on (default alpha5; on --resume, the run's): bravo7 trains its "
        "six joints G F E D C B with the preset's recipe, its base joint G as the weak one, "
        "its own workspace, and no envelope arms or parameter perturbation (they perturb "
        'the Alpha 5\'s parameters; docs/training.md, "Another arm")',
    )
    p.add_argument("--run", type=Path, help="run directory (checkpoints, logs)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=None, help="total env steps (preset default)")
    p.add_argument(
        "--until",
        type=int,
        default=None,
        help="stop (with a checkpoint) after this many env steps in total",
    )
    p.add_argument(
        "--hours",
        type=float,
        default=None,
        help="stop (with a checkpoint) after this much wall time in this process",
    )
    p.add_argument("--resume", action="store_true", help="continue from RUN/checkpoint.pt")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=JSON",
        help="override a config field, e.g. --set batch_size=128 "
        "--set env.reward.velocity_weight=1.0 (repeatable)",
    )
    p.add_argument("--checkpoint-minutes", type=float, default=10.0)
    p.add_argument("--no-progress", action="store_true", help="log lines instead of a bar")
    p.add_argument(
        "--evaluate",
        metavar="WEIGHTS",
        default=None,
        help="score an actor (.npz path; 'shipped' for the `ddpg` actor, "
        "policy/controllers/weights/ddpg_actor.npz; 'distilled' for the actor of "
        "ddpg-distilled; or 'expert' for the PD demonstrator) on --episodes fixed episodes "
        "with sensor noise, nominal and with E at 25%% torque, print the metrics as JSON, "
        "then exit",
    )
    p.add_argument("--episodes", type=int, default=20, help="episodes for --evaluate")
    p.add_argument(
        "--expert-energy",
        type=float,
        default=None,
        metavar="LAMBDA",
        help="with --evaluate expert: the energy-aware demonstrator "
        "(PDExpert.energy_lambda, N m/s; the shipped weights used 6)",
    )
    p.add_argument(
        "--perturb",
        type=float,
        default=0.0,
        metavar="SPREAD",
        help="with --evaluate: also score on arms whose friction, armature, masses "
        "and buoyancy are scaled by U(1 - SPREAD, 1 + SPREAD) per episode",
    )
    p.add_argument(
        "--envelope",
        type=int,
        default=None,
        metavar="N",
        help="with --evaluate WEIGHTS|shipped|distilled: run the `ddpg` controller (the actor "
        "alone, its memory channels kept as in training) with those weights, or with "
        "--distilled `ddpg-distilled` (actor + reference integral + settle supervisor; with "
        "--pure `ddpg-distilled-pure`, its actor alone) on N arms drawn from the uncertainty "
        "envelope (policy.tasks.envelope.draws(N, --envelope-seed)), one episode each "
        "(random_episodes(N, --episode-seed)), sensor noise on; print reached / at rest / "
        "overshoot as JSON",
    )
    p.add_argument("--envelope-seed", type=int, default=1, help="seed of the envelope draws")
    p.add_argument("--episode-seed", type=int, default=5, help="seed of the envelope episodes")
    p.add_argument("--distilled", action="store_true", help="with --envelope: run ddpg-distilled")
    p.add_argument("--pure", action="store_true", help="with --envelope: run ddpg-distilled-pure")
    p.add_argument(
        "--params",
        type=Path,
        metavar="FILE.json",
        help="train (or --evaluate) on the arm this parameter file describes (ArmParams "
        "field names, any subset, E D C B; as tools/identify.py writes) instead of the "
        "nominal model; --perturb and the env's param_perturbation spread around it",
    )
    p.add_argument(
        "--ship-as",
        type=Path,
        default=None,
        metavar="FILE.npz",
        help="with --ship: write the actor (+ .json) here instead of the shipped weights, "
        "e.g. a candidate that does not meet the bar "
        "(policy/controllers/weights/ddpg_distilled_robust_actor.npz)",
    )
    p.add_argument(
        "--ship",
        action="store_true",
        help="copy RUN's best actor to policy/controllers/weights/ddpg_actor.npz, the `ddpg` "
        "controller's weights (+ .json with its provenance: the commands, seed, config, "
        "training time and evaluation), then exit",
    )
    return p.parse_args(argv)


def evaluate_envelope(args: argparse.Namespace) -> dict[str, Any]:
    """`--evaluate WEIGHTS --envelope N`: the controller on N envelope arms."""
    if args.evaluate == "expert":
        raise SystemExit("--envelope: the expert reads the env's true state; give weights")
    if args.envelope < 1:
        raise SystemExit(f"--envelope needs N >= 1, got {args.envelope}")
    path = weights_path(args.evaluate)
    name = "ddpg-distilled-pure" if args.pure else "ddpg-distilled" if args.distilled else "ddpg"
    try:
        controller = load_controller(name, weights=str(path))
    except DriverError as exc:
        raise SystemExit(f"--evaluate: {exc}") from exc
    t0 = time.monotonic()
    results = envelope_results(controller, args.envelope, args.envelope_seed, args.episode_seed)
    return {
        "controller": name,
        "weights": str(path),
        "draws": f"policy.tasks.envelope.draws({args.envelope}, {args.envelope_seed})",
        "episodes": f"random_episodes({args.envelope}, {args.episode_seed})",
        "wall_s": round(time.monotonic() - t0, 1),
        **envelope_summary(results),
    }


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    arm = None if args.arm is None else model_named(args.arm)
    if arm is not None and arm is not ALPHA5 and (args.params or args.evaluate):
        raise SystemExit(
            f"--arm {arm.name}: --params and --evaluate are the Alpha 5's (its parameters, "
            "its evaluation sets)"
        )
    arm_factory = params_arm_factory(args.params)
    if args.evaluate is not None and args.envelope is not None:
        print(json.dumps(evaluate_envelope(args), indent=1))
        return 0
    if args.evaluate is not None:
        result = evaluate_weights(
            args.evaluate, args.episodes, args.seed, args.perturb, args.expert_energy, arm_factory
        )
        print(json.dumps(result, indent=1))
        return 0
    if args.run is None:
        raise SystemExit("--run is required (except with --evaluate)")
    run_dir: Path = args.run
    if args.ship:
        verb = "wrote" if args.ship_as else "shipped"
        print(f"{verb} {ship(run_dir, args.ship_as or LEARNED_WEIGHTS)}")
        return 0
    start = start_run(run_dir, args.resume, args.config, args.seed, args.steps, args.set, arm)
    if not args.resume and arm is not None and arm is not ALPHA5:
        env = start.config.env
        print(
            f"{arm.title}: {arm.n_joints} joints {' '.join(arm.joint_letters)}; envelope "
            f"arms {env.envelope_fraction:g}, param perturbation {env.param_perturbation:g} "
            "(the Alpha 5's parameters only)"
        )
    record_command(run_dir, argv or sys.argv[1:])
    # every command the run was given (the start, then each resume): the actor's provenance
    command = "; ".join((run_dir / COMMANDS).read_text().splitlines())
    sitting = Sitting(args.until, args.hours, args.checkpoint_minutes, bar=not args.no_progress)
    return train_run(run_dir, start, args.resume, arm_factory, sitting, command)


if __name__ == "__main__":
    raise SystemExit(main())
