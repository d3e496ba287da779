"""The paper's scenario figures: controllers overlaid, per joint, position, torque and error."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from policy.campaigns.evaluation import EpisodeResult, RunConfig
from policy.tasks.scenarios import Scenario
from protocol.alpha5 import JOINT_LETTERS
from reach_driver.metrics import settling_band

#: overlaid in the scenario figures, in this order (when run)
FIGURE_CONTROLLERS = ("ddpg", "mpc", "pid")
COLORS = {
    "pid": "tab:green",
    "mpc": "tab:blue",
    "ddpg": "tab:red",
    "ddpg-distilled": "tab:purple",
    "ddpg-distilled-pure": "tab:orange",
}


JOINT_NAMES = tuple(f"{letter} (paper joint {j + 1})" for j, letter in enumerate(JOINT_LETTERS))


def plot_scenario(
    results: dict[str, EpisodeResult], sc: Scenario, path: Path, config: RunConfig
) -> None:
    """Controllers overlaid: per joint (columns E D C B) the position against its target,
    the torque, and |error| on a log scale with the settling band."""
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 4, figsize=(17, 9.5), sharex=True, constrained_layout=True)
    first = next(iter(results.values()))
    target = np.asarray(first.trace.target, dtype=float)
    band = settling_band(target - first.trace.q[0])
    for name, r in results.items():
        tr = r.trace
        t = tr.times
        color = COLORS.get(name)
        err = np.maximum(np.abs(tr.errors), 1e-6)  # log scale: exact zeros drawn at 1 urad
        for j in range(4):
            axes[0, j].plot(t, tr.q[:, j], color=color, lw=1.2, label=name)
            axes[1, j].plot(t, tr.tau[:, j], color=color, lw=1.0, label=name)
            axes[2, j].semilogy(t, err[:, j], color=color, lw=1.0, label=name)
    for j in range(4):
        axes[0, j].axhline(target[j], color="k", ls="--", lw=0.8, label="target")
        axes[2, j].axhline(band[j], color="0.4", ls=":", lw=1.0, label="settling band")
        axes[2, j].set_ylim(1e-5, None)
        axes[0, j].set_title(JOINT_NAMES[j])
        axes[2, j].set_xlabel("time [s]")
    axes[0, 0].set_ylabel("position [rad, arm angle]")
    axes[1, 0].set_ylabel("torque [N m]")
    axes[2, 0].set_ylabel("|error| [rad]")
    for ax in axes.flat:
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="best")
    torque = "" if all(s == 1.0 for s in sc.torque_scale) else f", torque scale {sc.torque_scale}"
    fig.suptitle(
        f"Scenario {sc.number} ({sc.title}): {', '.join(results)}; nominal arm, no noise, "
        f"{config.seconds:g} s at {config.rate_hz:g} Hz; paper x_ref = {sc.paper_target}, "
        f"arm target (E D C B) = ({', '.join(f'{v:.3f}' for v in target)}){torque}"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80, metadata={"Software": None})  # no version stamp: same bytes
    plt.close(fig)
