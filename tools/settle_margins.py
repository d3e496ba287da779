#!/usr/bin/env python3
"""Stability margins of the settle law's linear part (policy/controllers/settle.py) over the
envelope.

The loop per joint: kt (kp + kd s + ki / s) e^(-s tau) / (J s^2 + b s), kt the torque per
amp, J the joint's inertia (the MuJoCo mass matrix's diagonal, 0.12-0.16 kg m^2 on E D C and
0.007 on B, times the envelope's armature x0.5-1.5), b its viscous friction (the model's
damping x0.5-1.5), tau the loop delay (half a 50 ms period of hold plus 0-2 periods of
latency: 25-130 ms). Coulomb friction is left out: it only adds damping. Prints the worst
phase margin (degrees) and gain margin over a grid of J, b and tau for the given gains.

    tools/settle_margins.py                       # the defaults of policy.controllers.settle_law
    tools/settle_margins.py --kp 200 200 100 100 --kd 20 20 20 10 --ki 60 60 30 30
"""

from __future__ import annotations

import argparse
import itertools

import numpy as np

from policy.controllers.settle_law import DEFAULT_KD, DEFAULT_KI, DEFAULT_KP
from protocol.alpha5 import JOINT_LETTERS, TORQUE_PER_AMP_NM

INERTIA = ((0.06, 0.23), (0.066, 0.23), (0.062, 0.19), (0.0035, 0.0107))  # kg m^2
VISCOUS = ((1.2, 3.6), (1.12, 3.36), (0.41, 1.23), (0.18, 0.54))  # N m s/rad
DELAYS = (0.025, 0.075, 0.13)  # s


def margins(
    kp: float, kd: float, ki: float, kt: float, j: float, b: float, tau: float
) -> tuple[float, float]:
    """(phase margin in degrees, gain margin) of the loop; gains in A/rad, A/(rad/s)..."""
    w = np.logspace(-2, 2.5, 20000)
    s = 1j * w
    loop = kt * (kp + kd * s + ki / s) * np.exp(-s * tau) / (j * s**2 + b * s)
    mag = np.abs(loop)
    phase = np.unwrap(np.angle(loop))
    cross = np.where(np.diff(np.sign(mag - 1.0)))[0]
    pm = min(float(np.degrees(phase[k])) + 180.0 for k in cross) if len(cross) else 180.0
    flip = np.where(np.diff(np.sign(phase + np.pi)))[0]
    gm = min(float(1.0 / mag[k]) for k in flip) if len(flip) else float("inf")
    return pm, gm


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--kp", type=float, nargs=4, default=DEFAULT_KP, help="mA/rad, E D C B")
    p.add_argument("--kd", type=float, nargs=4, default=DEFAULT_KD, help="mA/(rad/s)")
    p.add_argument("--ki", type=float, nargs=4, default=DEFAULT_KI, help="mA/(rad s)")
    args = p.parse_args()
    for i, letter in enumerate(JOINT_LETTERS[:4]):
        worst_pm, worst_gm = 180.0, float("inf")
        grid = itertools.product(np.linspace(*INERTIA[i], 3), np.linspace(*VISCOUS[i], 3), DELAYS)
        for j, b, tau in grid:
            pm, gm = margins(
                args.kp[i] / 1000,
                args.kd[i] / 1000,
                args.ki[i] / 1000,
                float(TORQUE_PER_AMP_NM[i]),
                float(j),
                float(b),
                tau,
            )
            worst_pm, worst_gm = min(worst_pm, pm), min(worst_gm, gm)
        print(
            f"{letter}: kp {args.kp[i]:g} kd {args.kd[i]:g} ki {args.ki[i]:g}: worst phase "
            f"margin {worst_pm:.0f} deg, gain margin {worst_gm:.2f}"
        )


if __name__ == "__main__":
    main()
