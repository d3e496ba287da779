"""The gap a fitted twin closes: a controller's metrics on the hidden arm, the fitted twin and
the nominal twin, on the same episodes (`measure_gap`, `markdown`).

Why: a twin is for predicting what a controller does on the arm. The issue's target is that a
controller's energy on the fitted twin is within 5 % of its energy on the arm, and its
settling time within 0.1 s; parameter errors and trajectory RMS say nothing about that
directly. Each controller runs every episode on each arm through `policy.campaigns.evaluation`'s
`DirectArm` backend (the physics the training environment and `tools/evaluate.py` use, no
link delay), scored by `reach_driver.metrics`. A virtual arm only: the "hidden" arm is an arm
parameter file (the one `reach-sim --params` served to the identification).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from policy.campaigns.evaluation import (
    DirectArm,
    Episode,
    RunConfig,
    evaluate,
    load_controller,
)
from reach_sim_bridge.model.params import ArmParams

ENERGY_TOL = 0.05
"""The issue's target: fitted-twin energy within this fraction of the hidden arm's."""
SETTLING_TOL_S = 0.1
"""... and settling time within this many seconds."""
TWINS = ("hidden", "fitted", "nominal")
DEFAULT_CONTROLLERS = ("pid", "ddpg-distilled")


@dataclass(frozen=True)
class EpisodeGap:
    """One episode of one controller on the three arms."""

    episode: int
    energy_j: dict[str, float]  # hidden, fitted, nominal
    settling_s: dict[str, float]
    reached: dict[str, bool]

    def energy_error(self, twin: str) -> float:
        """|twin - hidden| / hidden."""
        hidden = self.energy_j["hidden"]
        return abs(self.energy_j[twin] - hidden) / max(abs(hidden), 1e-9)

    def settling_error(self, twin: str) -> float:
        """|twin - hidden| in s, to the microsecond: settling times lie on the control ticks,
        and 4.40 - 4.30 is 0.10000000000000053 in floating point, past `SETTLING_TOL_S`."""
        return round(abs(self.settling_s[twin] - self.settling_s["hidden"]), 6)


@dataclass(frozen=True)
class ControllerGap:
    """A controller's episodes, and how far each twin's metrics are from the hidden arm's."""

    controller: str
    episodes: tuple[EpisodeGap, ...]

    def worst_energy(self, twin: str) -> float:
        return max(e.energy_error(twin) for e in self.episodes)

    def mean_energy(self, twin: str) -> float:
        return float(np.mean([e.energy_error(twin) for e in self.episodes]))

    def worst_settling(self, twin: str) -> float:
        return max(e.settling_error(twin) for e in self.episodes)

    def mean_settling(self, twin: str) -> float:
        return float(np.mean([e.settling_error(twin) for e in self.episodes]))

    def meets_targets(self, twin: str = "fitted") -> bool:
        """Every episode within ENERGY_TOL and SETTLING_TOL_S of the hidden arm."""
        return self.worst_energy(twin) <= ENERGY_TOL and self.worst_settling(twin) <= (
            SETTLING_TOL_S
        )

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {"controller": self.controller, "episodes": len(self.episodes)}
        for twin in ("fitted", "nominal"):
            out[twin] = {
                "energy_error_max": self.worst_energy(twin),
                "energy_error_mean": self.mean_energy(twin),
                "settling_error_max_s": finite_or_none(self.worst_settling(twin)),
                "settling_error_mean_s": finite_or_none(self.mean_settling(twin)),
                "meets_targets": self.meets_targets(twin),
            }
        return out


def finite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None


def measure_gap(
    controllers: Sequence[str],
    hidden: ArmParams,
    fitted: ArmParams,
    episodes: Sequence[Episode],
    config: RunConfig | None = None,
    nominal: ArmParams | None = None,
    on_episode: Callable[[str, str, int], None] | None = None,
) -> list[ControllerGap]:
    """Run each controller on every episode on the hidden, fitted and nominal arm (the same
    episodes, seeds and controller settings) and pair the metrics up per episode."""
    base = config or RunConfig()
    arms = {"hidden": hidden, "fitted": fitted, "nominal": nominal or ArmParams()}
    out = []
    for name in controllers:
        controller = load_controller(name)
        runs: dict[str, Any] = {}
        for twin in TWINS:
            cfg = RunConfig(
                seconds=base.seconds,
                rate_hz=base.rate_hz,
                seed=base.seed,
                physics_dt=base.physics_dt,
                params=arms[twin],
            )

            def note(i: int, _r: Any, twin: str = twin, name: str = name) -> None:
                if on_episode is not None:
                    on_episode(name, twin, i)

            runs[twin] = evaluate(
                controller, episodes, cfg, name=name, backend=DirectArm(), on_episode=note
            )
        gaps = []
        for i in range(len(episodes)):
            m = {twin: runs[twin].results[i].metrics for twin in TWINS}
            gaps.append(
                EpisodeGap(
                    episode=i,
                    energy_j={t: float(m[t].energy_j) for t in TWINS},
                    # An episode that never settles scores the episode's length.
                    settling_s={t: float(m[t].settling_time_s) for t in TWINS},
                    reached={t: bool(m[t].reached) for t in TWINS},
                )
            )
        out.append(ControllerGap(name, tuple(gaps)))
    return out


def markdown(gaps: Sequence[ControllerGap]) -> str:
    """Per controller: each episode's energy and settling time on the three arms, the
    fitted and nominal twins' errors, and whether the targets are met."""
    lines = [
        "## Controller metrics: hidden arm, fitted twin, nominal twin",
        "",
        f"Targets: fitted-twin energy within {ENERGY_TOL:.0%} and settling time within "
        f"{SETTLING_TOL_S:g} s of the hidden arm's (DirectArm backend, same episodes).",
        "",
    ]
    for g in gaps:
        lines += [
            f"### {g.controller}",
            "",
            "| episode | energy J hidden / fitted / nominal | energy error fitted / nominal | "
            "settling s hidden / fitted / nominal | settling error fitted / nominal |",
            "|---|---|---|---|---|",
        ]
        for e in g.episodes:
            en, st = e.energy_j, e.settling_s
            err_f, err_n = 100 * e.energy_error("fitted"), 100 * e.energy_error("nominal")
            lines.append(
                f"| {e.episode} | {en['hidden']:.3f} / {en['fitted']:.3f} / {en['nominal']:.3f} "
                f"| {err_f:.2f} % / {err_n:.2f} % "
                f"| {st['hidden']:.2f} / {st['fitted']:.2f} / {st['nominal']:.2f} "
                f"| {e.settling_error('fitted'):.3f} / {e.settling_error('nominal'):.3f} |"
            )
        lines += [
            "",
            f"Worst episode: energy {100 * g.worst_energy('fitted'):.2f} % fitted against "
            f"{100 * g.worst_energy('nominal'):.2f} % nominal; settling "
            f"{g.worst_settling('fitted'):.3f} s against {g.worst_settling('nominal'):.3f} s. "
            f"Targets {'met' if g.meets_targets() else '**not met**'} by the fitted twin.",
            "",
        ]
    return "\n".join(lines) + "\n"
