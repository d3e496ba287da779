"""Training throughput: our DDPG loop against Stable-Baselines3 DDPG, same networks, same env.

    .venv/bin/python tools/bench_train.py              # ~2-3 minutes on one core
    .venv/bin/python tools/bench_train.py --steps 2000 --rounds 1

Every contender trains on ReachAlpha-v0 (paper observation and reward) with 400-300 LeakyReLU
actor and critic, in this one process, one torch thread, after a warm-up that fills the replay
buffer. Contenders run in interleaved rounds so load from other processes hits all of them
alike; the figure per contender is its median over rounds. Reported: env steps/s, gradient
updates/s and transitions learned from per second (updates x batch), each as a ratio to SB3.

Contenders:
  sb3     SB3 DDPG, batch 64, one update per env step (train_freq 1, gradient_steps 1)
  paper   our loop with the paper's settings: 1 env, batch 64, one update per step
  ours    our loop as the distilled stack's first stage trained: 8 envs per round, batch
          256, 2 updates per round (the paper's 64 transitions learned from per env step),
          twin critics
  scratch the `scratch` preset's learner and env (DDPG updates, memory channels, shaped
          reward, envelope arms): 256-256 networks, 16 envs per round, batch 256, 2
          updates per round (32 transitions per env step), the envs in this process
  scratch+collector  the preset as it trains the shipped `ddpg`: the same with
          `collector_process`, the envs in a second process one round ahead of the
          learner (on one core this only adds the hand-over)
  scratch+crossq  `scratch` with the `crossq` ingredient (CrossQ's batch-renormalised
          critic without target networks, s and s' in one batch, the actor every third
          update), the envs in this process
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from collections.abc import Callable

import numpy as np
import torch

from policy.rl.config import DDPGConfig
from policy.rl.env import EnvConfig, ReachAlphaEnv, time_limited
from policy.rl.trainer import Trainer


def bench_ours(
    config: DDPGConfig, warmup: int, steps: int, run_dir: str, trainers: list[Trainer]
) -> Callable[[], dict[str, float]]:
    """Rounds of `steps` env steps of our training loop; the trainer joins `trainers` (to be
    closed at the end: `collector_process` keeps a child process)."""
    trainer = Trainer(config, run_dir, log=lambda _: None)
    trainers.append(trainer)
    trainer.run(until_steps=warmup)

    def one_round() -> dict[str, float]:
        start_steps, start_updates = trainer.state.env_steps, trainer.agent.updates
        t0 = time.perf_counter()
        trainer.run(until_steps=start_steps + steps)
        dt = time.perf_counter() - t0
        updates = trainer.agent.updates - start_updates
        return {
            "env_steps_s": (trainer.state.env_steps - start_steps) / dt,
            "updates_s": updates / dt,
            "samples_s": updates * config.batch_size / dt,
        }

    return one_round


def bench_sb3(
    env_config: EnvConfig, warmup: int, steps: int, seed: int
) -> Callable[[], dict[str, float]]:
    try:
        from stable_baselines3 import DDPG
        from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise
    except ImportError:
        raise SystemExit(
            "bench_train.py compares against Stable-Baselines3, which the bench extra installs: "
            "make bench (or pip install -e '.[bench]')"
        ) from None

    env = time_limited(ReachAlphaEnv(env_config))  # as gym.make builds it: SB3 needs the limit
    noise = OrnsteinUhlenbeckActionNoise(np.zeros(4), 0.2 * np.ones(4))
    model = DDPG(
        "MlpPolicy",
        env,
        learning_rate=1e-3,
        buffer_size=200_000,
        learning_starts=warmup,
        batch_size=64,
        tau=0.001,
        gamma=0.99,
        train_freq=1,
        gradient_steps=1,
        action_noise=noise,
        seed=seed,
        device="cpu",
        verbose=0,
        policy_kwargs={
            "net_arch": {"pi": [400, 300], "qf": [400, 300]},
            "activation_fn": torch.nn.LeakyReLU,
        },
    )
    model.learn(total_timesteps=warmup + 1)

    def one_round() -> dict[str, float]:
        start_steps, start_updates = model.num_timesteps, model._n_updates
        t0 = time.perf_counter()
        model.learn(total_timesteps=steps, reset_num_timesteps=False)
        dt = time.perf_counter() - t0
        updates = model._n_updates - start_updates
        return {
            "env_steps_s": (model.num_timesteps - start_steps) / dt,
            "updates_s": updates / dt,
            "samples_s": updates * 64 / dt,
        }

    return one_round


def bench_inference(n: int) -> None:
    """Latency of one control-loop action: the shipped numpy controller (actor, reference
    integral, settle supervisor), the same without the supervisor, and the torch actor."""
    from policy.controllers.ddpg_distilled import make_controller
    from policy.controllers.weights import DISTILLED_WEIGHTS
    from policy.rl.checkpoint import load_actor_npz
    from policy.rl.networks import Actor
    from reach_driver.controllers import ControlState

    ctrl = make_controller()
    bare = make_controller(settle=False)
    w = ctrl.weights
    actor = Actor(w.weights[0].shape[1], 4, (w.weights[0].shape[0], w.weights[1].shape[0]))
    load_actor_npz(actor, DISTILLED_WEIGHTS)
    rng = np.random.default_rng(0)
    states = [
        ControlState(q=rng.uniform(0.5, 2.8, 4), qdot=rng.normal(0, 0.5, 4), t=0.05 * k)
        for k in range(n)
    ]
    target = np.array([3.0, 1.7, 1.7, 1.6])

    def numpy_act(s: ControlState) -> np.ndarray:
        return ctrl.act(s, target)

    def bare_act(s: ControlState) -> np.ndarray:
        return bare.act(s, target)

    def torch_act(s: ControlState) -> np.ndarray:
        obs = torch.from_numpy(ctrl.observation(s, target))
        with torch.no_grad():
            out: np.ndarray = actor(obs).numpy() * ctrl.current_limits_mA
        return out

    print(f"\n{'inference':<22} {'p50 us':>8} {'p99 us':>8} {'max us':>8}")
    contenders = (
        ("ddpg-distilled act (shipped)", numpy_act),
        ("ddpg-distilled act, settle=0", bare_act),
        ("torch actor + obs", torch_act),
    )
    for name, fn in contenders:
        for s in states[:200]:
            fn(s)
        times = np.empty(n)
        for i, s in enumerate(states):
            t0 = time.perf_counter()
            fn(s)
            times[i] = time.perf_counter() - t0
        p50, p99, mx = (1e6 * np.percentile(times, q) for q in (50, 99, 100))
        print(f"{name:<22} {p50:>8.1f} {p99:>8.1f} {mx:>8.1f}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--steps", type=int, default=3000, help="env steps per contender per round")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--warmup", type=int, default=1000, help="env steps before timing")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--inference",
        type=int,
        default=0,
        metavar="N",
        help="only time N single actions of the shipped controller (numpy), the same "
        "without its settle supervisor and the torch actor with the same weights, then exit",
    )
    args = p.parse_args(argv)
    if args.inference:
        torch.set_num_threads(1)
        bench_inference(args.inference)
        return 0
    if args.steps < 100 or args.rounds < 1 or args.warmup < 100:
        raise SystemExit("--steps and --warmup must be >= 100, --rounds >= 1")
    torch.set_num_threads(1)

    paper = DDPGConfig.paper(
        seed=args.seed,
        learning_starts=args.warmup,
        eval_every=10**9,
        total_steps=10**9,
        buffer_size=200_000,
    )
    ours_cfg = DDPGConfig.ours()
    ours = dataclasses.replace(
        paper,
        name="ours-throughput",
        num_envs=ours_cfg.num_envs,
        batch_size=ours_cfg.batch_size,
        updates_per_round=ours_cfg.updates_per_round,
        twin_critics=True,
        policy_delay=2,
        target_noise=0.1,
        tau=0.005,
    )
    scratch = DDPGConfig.scratch(
        seed=args.seed,
        learning_starts=args.warmup,
        eval_every=10**9,
        total_steps=10**9,
        buffer_size=200_000,
        eval_envelope_episodes=0,
        collector_process=False,
    )
    tmp = tempfile.TemporaryDirectory()
    trainers: list[Trainer] = []
    contenders: dict[str, Callable[[], dict[str, float]]] = {
        "sb3": bench_sb3(paper.env, args.warmup, args.steps, args.seed),
        "paper": bench_ours(paper, args.warmup, args.steps, tmp.name + "/paper", trainers),
        "ours": bench_ours(ours, args.warmup, args.steps, tmp.name + "/ours", trainers),
        "scratch": bench_ours(scratch, args.warmup, args.steps, tmp.name + "/scratch", trainers),
        "scratch+collector": bench_ours(
            dataclasses.replace(scratch, collector_process=True),
            args.warmup,
            args.steps,
            tmp.name + "/collector",
            trainers,
        ),
        "scratch+crossq": bench_ours(
            dataclasses.replace(scratch, crossq_critic=True, adam_beta1=0.5, policy_delay=3),
            args.warmup,
            args.steps,
            tmp.name + "/crossq",
            trainers,
        ),
    }
    results: dict[str, list[dict[str, float]]] = {name: [] for name in contenders}
    for r in range(args.rounds):
        for name, one_round in contenders.items():
            results[name].append(one_round())
        print(f"round {r + 1}/{args.rounds} done", flush=True)

    def median(name: str, key: str) -> float:
        return statistics.median(x[key] for x in results[name])

    print(
        f"\n{'contender':<18} {'env steps/s':>12} {'updates/s':>10} {'samples/s':>10}"
        f" {'x SB3 steps':>12} {'x SB3 samples':>14}"
    )
    base_steps, base_samples = median("sb3", "env_steps_s"), median("sb3", "samples_s")
    for name in contenders:
        s, u, n = (median(name, k) for k in ("env_steps_s", "updates_s", "samples_s"))
        print(
            f"{name:<18} {s:>12.0f} {u:>10.0f} {n:>10.0f} {s / base_steps:>12.2f}"
            f" {n / base_samples:>14.2f}"
        )
    for trainer in trainers:
        trainer.close()
    tmp.cleanup()
    print(
        f"\n(medians of {args.rounds} rounds of {args.steps} env steps; torch "
        f"{torch.__version__}, 1 thread)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
