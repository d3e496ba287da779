"""The excitation run on a virtual arm in this process: the controller, plan and amplitude
adaptation `driving.excite` uses through the driver, with `Alpha5Arm` stepped directly
(`excite_virtual`). Why: the identifiability figures (docs/identification.md, "What the data
cannot tell apart") are about the physics, not the link, and a campaign through the driver on
a loaded host loses arms to host stalls; this takes seconds per arm and is the same on every
host. Each command lands a fixed number of physics steps after its tick, and the segment
carries that delay as the driver's timestamps would have measured it."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from policy.controllers.excitation import Amplitudes, Excitation, Wave, pose
from protocol.alpha5 import JOINT_LETTERS, N_JOINTS
from reach_driver.controllers import ControlState
from reach_sim_bridge.fit.segments import Segment, segment_suffix
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import ArmParams
from reach_sim_bridge.model.sensors import SensorNoise

DELAY_STEPS = 2
"""Physics steps (2 ms each) between a tick and its command landing: 4 ms, about the median a
loaded host's link measured (docs/identification.md)."""


def excite_virtual(
    params: ArmParams,
    joints: Sequence[int],
    waves: Sequence[Wave],
    *,
    rate_hz: float = 50.0,
    noise: SensorNoise | None = None,
    seed: int = 0,
    max_current_mA: float = 300.0,
    delay_steps: int = DELAY_STEPS,
) -> list[Segment]:
    """Every wave on every joint of the arm `params`, as `tools/identify.py` runs them: each
    segment from rest at its pose, the other joints held by the excitation's PID, readings with
    `noise` (seeded by `seed`), currents capped at 80 % of `max_current_mA` (B: half of it).
    Segments are tagged with the load `params` holds in its jaws (`payload_kg`)."""
    arm = Alpha5Arm(params=params)
    # the hold's gravity feed-forward knows the load the arm holds (`ArmParams.payload_kg`)
    twin = Alpha5Arm(
        ArmParams(payload_kg=params.payload_kg, payload_volume_l=params.payload_volume_l)
    )
    suffix = segment_suffix(params.payload_kg)
    substeps = int(round(1.0 / (rate_hz * arm.dt)))
    if substeps < 1 or not 0 <= delay_steps < substeps:
        raise ValueError(f"delay of {delay_steps} steps does not fit a {1 / rate_hz:g} s tick")
    period = substeps * arm.dt
    sensor = noise or SensorNoise(0.0, 0.0)
    rng = np.random.default_rng(seed)
    caps = np.array([1.0, 1.0, 1.0, 0.5]) * max_current_mA
    amps = Amplitudes()
    out: list[Segment] = []
    for j in joints:
        for k, wave in enumerate(waves):
            center = pose(wave.pose)
            start = amps.start(j, wave.speed) if wave.kind == "relay" else amps.reference(j)
            ctl = Excitation(j, wave, center, period, start, 0.8 * caps[j], twin.gravity_torque)
            arm.reset(q=center)
            n = int(round(wave.seconds / period))
            q = np.empty((n + 1, N_JOINTS))
            qd = np.empty((n + 1, N_JOINTS))
            cmd = np.zeros((n + 1, N_JOINTS))
            cur = np.zeros((n + 1, N_JOINTS))
            q[0], qd[0] = sensor.apply(arm.q, arm.qdot, rng)
            held = np.zeros(N_JOINTS)
            for i in range(n):
                u = np.clip(ctl.act(ControlState(q[i], qd[i], i * period), center), -caps, caps)
                if delay_steps:
                    arm.step(held, n=delay_steps)
                arm.step(u, n=substeps - delay_steps)
                held = u
                cmd[i + 1] = u
                cur[i + 1] = arm.current_mA
                q[i + 1], qd[i + 1] = sensor.apply(arm.q, arm.qdot, rng)
            if wave.kind == "relay":
                amps.learn(j, wave.speed, ctl.amplitude)
            out.append(
                Segment(
                    name=f"{JOINT_LETTERS[j]}{k}-{wave.kind}-{wave.pose}{suffix}",
                    joint=j,
                    role=wave.role,
                    period=period,
                    q=q,
                    qdot=qd,
                    command_mA=cmd,
                    current_mA=cur,
                    meta={
                        "wave": wave.label,
                        "pose": center.tolist(),
                        "amplitude_mA": ctl.amplitude,
                    },
                    # what the driver's timestamps would have measured (`link_delays`)
                    link_delay_s=np.full(n + 1, delay_steps * arm.dt),
                    payload_kg=params.payload_kg,
                    payload_volume_l=params.payload_volume_l,
                )
            )
    return out
