"""Train the DDPG controller on ReachAlpha-v0, with checkpoints that survive the session.

    .venv/bin/python tools/train.py --config ours --run runs/ours-s0 --seed 0
    .venv/bin/python tools/train.py --run runs/ours-s0 --resume          # continue later
    .venv/bin/python tools/train.py --config paper --run runs/paper-s0   # the paper's DDPG

Writes to the run directory: config.json, train.csv (one row per finished episode: return and
losses), eval.jsonl (periodic deterministic evaluation), best_actor.npz/.json (best evaluated
actor, the format policy/controllers/weights/ ships), checkpoint.pt + buffer.npz (everything to
resume), commands.txt (every command given), train.log (what was printed).

`--resume --set KEY=VALUE` applies the fields a resumed run can change (learning rates, batch
size, exploration, the BC schedule, evaluation cadence: `RESUMABLE`) and refuses, naming the
field and why, those it cannot (network sizes, the environment, the buffer, the seed...).
Ctrl-C or SIGTERM saves a checkpoint, then exits 130 (143 for SIGTERM).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from policy.campaigns.selection import envelope_results, envelope_summary
from policy.controllers.weights import DEFAULT_WEIGHTS, ActorWeights
from policy.rl.batched import evaluate_batched
from policy.rl.config import WEAK_EVAL_SEED_OFFSET, WEAK_EVAL_TORQUE_SCALE, DDPGConfig
from policy.rl.env import EnvConfig
from policy.rl.expert import PDExpert
from policy.rl.trainer import Trainer, TrainState, make_expert
from reach_driver.controllers import load_controller
from reach_driver.errors import DriverError
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import load_arm_params


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--config",
        default="ours",
        choices=["ours", "paper", "robust"],
        help="hyperparameter preset (policy.rl.config.DDPGConfig.ours / .paper / .robust)",
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
        help="score an actor (.npz path, 'shipped', or 'expert' for the PD "
        "demonstrator) on --episodes fixed episodes with sensor noise, nominal "
        "and with E at 25%% torque, print the metrics as JSON, then exit",
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
        help="with --evaluate WEIGHTS|shipped: run the `ddpg` controller as shipped (actor + "
        "reference integral; --pure: the actor alone) on N arms drawn from the uncertainty "
        "envelope (policy.tasks.envelope.draws(N, --envelope-seed)), one episode each "
        "(random_episodes(N, --episode-seed)), sensor noise on; print reached / at rest / "
        "overshoot as JSON",
    )
    p.add_argument("--envelope-seed", type=int, default=1, help="seed of the envelope draws")
    p.add_argument("--episode-seed", type=int, default=5, help="seed of the envelope episodes")
    p.add_argument("--pure", action="store_true", help="with --envelope: the actor alone")
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
        "(policy/controllers/weights/ddpg_robust_actor.npz)",
    )
    p.add_argument(
        "--ship",
        action="store_true",
        help="copy RUN's best actor to policy/controllers/weights/ddpg_actor.npz (+ .json with "
        "the commands, seed, config, training time and evaluation), then exit",
    )
    return p.parse_args(argv)


def params_arm_factory(path: Path | None) -> Any:
    """An env arm factory for the arm in a `--params` file (None: the env's nominal arm)."""
    if path is None:
        return None
    try:
        params = load_arm_params(path)
    except ValueError as exc:
        raise SystemExit(f"--params: {exc}") from exc

    def factory(config: EnvConfig) -> Any:
        return Alpha5Arm(params=params, dt=config.physics_dt)

    return factory


def evaluate_weights(
    which: str,
    episodes: int,
    seed: int,
    perturb: float = 0.0,
    expert_energy: float | None = None,
    arm_factory: Any = None,
) -> dict[str, Any]:
    """Metrics of an actor file (or the expert) on the fixed evaluation episodes."""
    env_config = DDPGConfig.ours().env
    policy: Any = None
    expert = None
    if which == "expert":
        expert = PDExpert(energy_lambda=expert_energy)
    else:
        path = DEFAULT_WEIGHTS if which == "shipped" else Path(which)
        try:
            weights = ActorWeights.load(path)
        except (OSError, ValueError) as exc:
            raise SystemExit(f"--evaluate: {exc}") from exc
        env_config = dataclasses.replace(
            EnvConfig.from_dict(weights.metadata["env"]), observation=weights.observation
        )
        policy = weights.forward
    eval_seed = DDPGConfig().eval_seed + seed
    nominal = evaluate_batched(
        policy, env_config, episodes, eval_seed, expert=expert, arm_factory=arm_factory
    )
    weak = evaluate_batched(
        policy,
        env_config,
        episodes,
        eval_seed + WEAK_EVAL_SEED_OFFSET,
        torque_scale=WEAK_EVAL_TORQUE_SCALE,
        expert=expert,
        arm_factory=arm_factory,
    )
    result = {
        "weights": which,
        "episodes": episodes,
        "eval_seed": eval_seed,
        "nominal": nominal.to_dict(),
        "torque_e_25pct": weak.to_dict(),
    }
    if perturb > 0:
        if not perturb < 1:
            raise SystemExit(f"--perturb must be in (0, 1), got {perturb}")
        result[f"perturbed_{perturb:g}"] = evaluate_batched(
            policy,
            env_config,
            episodes,
            eval_seed + 10_000,
            expert=expert,
            param_perturbation=perturb,
            arm_factory=arm_factory,
        ).to_dict()
    return result


def evaluate_envelope(args: argparse.Namespace) -> dict[str, Any]:
    """`--evaluate WEIGHTS --envelope N`: the controller on N envelope arms."""
    if args.evaluate == "expert":
        raise SystemExit("--envelope: the expert reads the env's true state; give weights")
    if args.envelope < 1:
        raise SystemExit(f"--envelope needs N >= 1, got {args.envelope}")
    path = DEFAULT_WEIGHTS if args.evaluate == "shipped" else Path(args.evaluate)
    name = "ddpg-pure" if args.pure else "ddpg"
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


def ship(run_dir: Path, dest: Path = DEFAULT_WEIGHTS) -> Path:
    """Copy the run's best evaluated actor, with how it was made, to the shipped weights."""
    src = run_dir / "best_actor.npz"
    if not src.exists():
        raise SystemExit(f"--ship: {src} does not exist (no evaluation yet?)")
    meta = json.loads(src.with_suffix(".json").read_text())
    commands = (
        (run_dir / "commands.txt").read_text().splitlines()
        if (run_dir / "commands.txt").exists()
        else []
    )
    meta.update(
        {
            "command": commands[0] if commands else None,
            "commands": commands,
            "seed": meta["config"]["seed"],
            "training_time_s": round(float(meta.get("wall_s", float("nan"))), 1),
            "training_env_steps": meta.get("env_steps"),
            "run": run_dir.name,
            "shipped_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
    )
    dest.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dest)
    dest.with_suffix(".json").write_text(json.dumps(meta, indent=1))
    return dest


def apply_overrides(config: DDPGConfig, overrides: list[str]) -> DDPGConfig:
    data = config.to_dict()
    for item in overrides:
        if "=" not in item:
            raise SystemExit(f"--set expects KEY=JSON, got {item!r}")
        key, raw = item.split("=", 1)
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        node: dict[str, Any] = data
        *path, leaf = key.split(".")
        for part in path:
            if part not in node or not isinstance(node[part], dict):
                raise SystemExit(f"--set: unknown key {key!r}")
            node = node[part]
        if leaf not in node:
            raise SystemExit(f"--set: unknown key {key!r}")
        node[leaf] = value
    try:
        return DDPGConfig.from_dict(data)
    except (TypeError, ValueError) as exc:
        raise SystemExit(f"--set: {exc}") from exc


#: `--resume --set` may change these: the trainer and the agent read them afresh at every
#: round (learning rates at the next update, the batch size at the next sample, exploration,
#: the BC schedule, evaluation cadence), so they take effect from the resumed step.
RESUMABLE = frozenset(
    {
        "total_steps",
        "actor_lr",
        "critic_lr",
        "lr_decay",
        "lr_decay_every",
        "batch_size",
        "tau",
        "gamma",
        "learning_starts",
        "ou_theta",
        "ou_sigma",
        "eps_start",
        "eps_end",
        "eps_steps",
        "updates_per_round",
        "target_noise",
        "target_noise_clip",
        "policy_delay",
        "demo_fraction",
        "bc_weight",
        "bc_weight_final",
        "bc_decay_steps",
        "bc_relative",
        "q_weight",
        "curriculum_start",
        "curriculum_steps",
        "eval_every",
        "score_energy_weight",
    }
)
#: ... and these it may not, with the reason given when one is asked for.
FIXED_ON_RESUME = {
    "name": "it names the preset the run started from",
    "seed": "it seeded the networks, buffers and envs the checkpoint continues",
    "env": "the replay buffer holds transitions of the old environment (its observation, "
    "reward and randomisation); start a new run, with init_actor to keep the actor",
    "hidden": "the checkpoint's networks have that shape",
    "twin_critics": "the checkpoint holds that many critics",
    "num_envs": "the envs, their exploration noise and their seeds are per env",
    "buffer_size": "the replay buffer in the checkpoint has that capacity",
    "demo_episodes": "the demonstrations were collected when the run started",
    "expert_energy_lambda": "the demonstrations and the expert actions in the buffer came "
    "from that demonstrator",
    "expert_kp": "the demonstrations and the expert actions in the buffer came from it",
    "expert_kd": "the demonstrations and the expert actions in the buffer came from it",
    "init_actor": "it is only read when a run starts",
    "eval_episodes": "the best actor's score was measured on those episodes",
    "eval_seed": "the best actor's score was measured on those episodes",
    "eval_envelope_episodes": "the best actor's score was measured on those arms",
    "bc_max_latency": "the expert labels in the buffer were kept or dropped by it",
}


def resume_overrides(config: DDPGConfig, overrides: list[str]) -> tuple[DDPGConfig, list[str]]:
    """`--set` on a resumed run: the config with the changes a resume can take, and what
    changed ("field old -> new"); SystemExit naming the field for one it cannot."""
    new = apply_overrides(config, overrides)
    old_d, new_d = config.to_dict(), new.to_dict()
    changed = []
    for name in old_d:
        if old_d[name] == new_d[name]:
            continue
        if name not in RESUMABLE:
            reason = FIXED_ON_RESUME.get(name, "it is fixed when a run starts")
            raise SystemExit(
                f"--resume --set: {name} cannot change on a resumed run ({reason}); it stays "
                f"{json.dumps(old_d[name])}. Changeable on resume: {', '.join(sorted(RESUMABLE))}"
            )
        changed.append(f"{name} {json.dumps(old_d[name])} -> {json.dumps(new_d[name])}")
    return new, changed


def apply_on_resume(trainer: Trainer, new: DDPGConfig) -> None:
    """Put the resumable fields of `new` into the running trainer (its config object is the
    agent's too), and into the exploration noise, which copied its parameters."""
    for name in RESUMABLE:
        setattr(trainer.config, name, getattr(new, name))
    trainer.noise.theta, trainer.noise.sigma = new.ou_theta, new.ou_sigma


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
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
        print(f"{verb} {ship(run_dir, args.ship_as or DEFAULT_WEIGHTS)}")
        return 0
    config_path = run_dir / "config.json"
    changes: list[str] = []
    if args.resume:
        if not (run_dir / "checkpoint.pt").exists():
            raise SystemExit(f"--resume: no checkpoint in {run_dir}")
        # The checkpoint's own config: what its networks and buffer were made with (config.json
        # may be newer, from a resume killed before it saved).
        saved = torch.load(run_dir / "checkpoint.pt", weights_only=False)["config"]
        config = DDPGConfig.from_dict(saved)
        target = config
        if args.set:
            target, changes = resume_overrides(config, args.set)
        if args.steps is not None:
            target.total_steps = args.steps
    else:
        if (run_dir / "checkpoint.pt").exists():
            raise SystemExit(f"{run_dir} already holds a run; use --resume or another --run")
        overrides: dict[str, Any] = {"seed": args.seed}
        if args.steps is not None:
            overrides["total_steps"] = args.steps
        config = target = apply_overrides(DDPGConfig.preset(args.config, **overrides), args.set)
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / "commands.txt", "a") as fh:
        fh.write(" ".join([".venv/bin/python", "tools/train.py", *(argv or sys.argv[1:])]) + "\n")

    console = Console(highlight=False)
    log_file = open(run_dir / "train.log", "a", buffering=1)  # noqa: SIM115

    def log(msg: str) -> None:
        """To train.log and stdout; printed through the console the progress bar draws on,
        so a line goes above the bar, never onto it."""
        line = f"[{time.strftime('%H:%M:%S')}] {msg}"
        log_file.write(line + "\n")
        console.print(line, markup=False, highlight=False, soft_wrap=True)
        console.file.flush()

    expert = make_expert(config)
    trainer = Trainer(config, run_dir, expert=expert, arm_factory=arm_factory, log=log)
    if args.resume:
        trainer.load()
        apply_on_resume(trainer, target)
        config = trainer.config
        config.total_steps = max(config.total_steps, trainer.state.env_steps)
        log(f"resumed at {trainer.state.env_steps} env steps")
        for change in changes:
            log(f"--set on resume: {change}")
    else:
        log(f"new run {run_dir} config={config.name} seed={config.seed}")
    config_path.write_text(json.dumps(config.to_dict(), indent=1))

    until = config.total_steps if args.until is None else args.until
    if until <= trainer.state.env_steps:
        raise SystemExit(f"--until {until}: the run is already at {trainer.state.env_steps} steps")
    deadline = time.monotonic() + args.hours * 3600 if args.hours else None
    stop_at = [until]
    last_print = [0.0]
    t0 = time.monotonic()
    steps0 = trainer.state.env_steps

    progress_bar = Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[detail]}"),
        console=console,
        disable=args.no_progress,
    )
    collects = (
        trainer.state.env_steps == 0
        and len(trainer.demos) == 0
        and config.demo_episodes > 0
        and expert is not None
    )
    demo_task = (
        progress_bar.add_task("demonstrations", total=config.demo_episodes, detail="episodes")
        if collects
        else None
    )
    train_task = progress_bar.add_task(
        "training", total=until, completed=trainer.state.env_steps, detail="", start=False
    )

    def on_demo(done: int, total: int) -> None:
        if demo_task is not None:
            progress_bar.update(demo_task, completed=done)
        if args.no_progress and (done == total or done % 10 == 0):
            log(f"demonstrations: {done}/{total} episodes")

    trainer.demo_progress = on_demo

    def progress(state: TrainState, losses: dict[str, float]) -> None:
        now = time.monotonic()
        if deadline is not None and now > deadline:
            stop_at[0] = state.env_steps
            raise _Stop
        if now - last_print[0] < (30.0 if args.no_progress else 0.25):
            return
        if last_print[0] == 0.0:
            progress_bar.start_task(train_task)
        last_print[0] = now
        detail = (
            f"critic {losses.get('critic_loss', np.nan):.3g} q {losses.get('q', np.nan):.3g} "
            f"eps {trainer.epsilon():.2f} bc {trainer.bc_weight():.2f}"
        )
        if args.no_progress:
            rate = (state.env_steps - steps0) / max(now - t0, 1e-9)
            eta = (until - state.env_steps) / max(rate, 1e-9)
            log(f"{state.env_steps}/{until} {rate:.0f} steps/s eta {eta / 60:.0f} min {detail}")
        else:
            progress_bar.update(train_task, completed=state.env_steps, detail=detail)

    interrupted: list[int] = []

    def on_signal(signum: int, frame: object) -> None:
        interrupted.append(signum)
        raise KeyboardInterrupt  # checkpoint below

    # SIGTERM checkpoints like Ctrl-C; a job started with `&` from a script ignores SIGINT, so
    # take it back too
    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        with progress_bar:
            trainer.run(
                until_steps=until,
                checkpoint_every_s=60 * args.checkpoint_minutes,
                progress=progress,
                csv_path=run_dir / "train.csv",
            )
            progress_bar.update(train_task, completed=trainer.state.env_steps)
    except _Stop:
        log(f"time limit reached at {stop_at[0]} env steps")
    except KeyboardInterrupt:
        name = signal.Signals(interrupted[0]).name if interrupted else "SIGINT"
        log(f"interrupted ({name}): saving a checkpoint")
    history = trainer.state.history
    if not history or history[-1]["env_steps"] != trainer.state.env_steps:
        trainer.evaluate_and_keep_best()
    trainer.save()
    log(
        f"checkpoint saved at {trainer.state.env_steps} env steps "
        f"({trainer.state.wall_s / 3600:.2f} h of training); best score "
        f"{trainer.state.best_score:.3f} -> {run_dir / 'best_actor.npz'}"
    )
    log_file.close()
    if interrupted:  # the shell's convention: 128 + the signal (130 for Ctrl-C, 143 for TERM)
        return 128 + interrupted[0]
    return 0


class _Stop(Exception):
    """Raised from the progress callback to end a run at its wall-time limit."""


if __name__ == "__main__":
    raise SystemExit(main())
