"""`--set KEY=JSON` on a training config: on a new run any field, on a resumed run only those
the running trainer reads afresh (`RESUMABLE`), the others refused with the reason
(`FIXED_ON_RESUME`). tools/train.py and tools/sweep.py share this one parser.

Errors are `SystemExit` naming the flag, as the command line reports them.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

from policy.rl.config import DDPGConfig

if TYPE_CHECKING:
    from policy.rl.trainer import Trainer


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
        "collector_process",
        "her_goals",
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
        "sac_target_entropy",
        "sac_alpha_lr",
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
    "algorithm": "the checkpoint's networks and optimisers are that algorithm's",
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
