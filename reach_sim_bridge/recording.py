"""`reach-sim --record FILE.rrd`: the virtual arm's true state as a Rerun recording.

The simulator sees what no client can: true joint angles, the current actually drawn, the
torque delivered. Sampling them at a fixed sim-time rate gives a ground-truth record to lay
beside the driver's own recording of the same run. Entity names follow the driver's
(`joints/<J>/position` = [q, firmware position setpoint], `torques`, `velocities`, `events`),
so `reach-driver inspect` reads either file; the 3D arm is a skeleton through the links' origins
computed by MuJoCo.
"""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from protocol import Mode
from protocol.alpha5 import JOINT_LETTERS as JOINTS
from reach_sim_bridge.arm import Alpha5Arm
from reach_sim_bridge.firmware import Firmware
from reach_sim_bridge.server import SimServer

DEVICE_IDS = (0x05, 0x04, 0x03, 0x02)


@dataclass(frozen=True)
class _Sample:
    t: float
    q: np.ndarray
    qdot: np.ndarray
    tau: np.ndarray
    drawn_mA: np.ndarray
    applied_mA: np.ndarray
    setpoint: np.ndarray
    modes: tuple[Mode, ...]
    skeleton: np.ndarray


def _sample(arm: Alpha5Arm, firmware: Firmware) -> _Sample:
    setpoints = [firmware.setpoints(dev) for dev in DEVICE_IDS]
    modes = tuple(m for m, _, _ in setpoints)
    target = np.array([p if m == Mode.POSITION else math.nan for m, p, _ in setpoints])
    return _Sample(
        t=arm.time,
        q=arm.q.copy(),
        qdot=arm.qdot.copy(),
        tau=arm.tau.copy(),
        drawn_mA=arm.current_mA.copy(),
        applied_mA=np.array([a for _, _, a in setpoints]),
        setpoint=target,
        modes=modes,
        skeleton=arm.skeleton(),
    )


class SimRecorder:
    """Samples a running SimServer at `rate_hz` of sim time into a .rrd, in its own thread."""

    def __init__(
        self,
        server: SimServer,
        path: str | Path,
        rate_hz: float = 50.0,
        flush_period_s: float = 0.5,
    ) -> None:
        if rate_hz <= 0:
            raise ValueError(f"recording rate must be positive, got {rate_hz}")
        self.server = server
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.period = 1.0 / rate_hz
        self.samples = 0
        self._flush_every = max(1, int(flush_period_s * rate_hz))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._rec = rr.RecordingStream("reach-sim", recording_id=f"reach-sim-{id(self)}")
        blueprint = rrb.Blueprint(
            rrb.Horizontal(
                rrb.Spatial3DView(origin="/", contents=["/arm/**"], name="arm (true state)"),
                rrb.Vertical(
                    *[
                        rrb.TimeSeriesView(
                            origin=f"/joints/{j}/position", name=f"{j}: position vs setpoint"
                        )
                        for j in JOINTS
                    ]
                ),
                rrb.Vertical(
                    rrb.TimeSeriesView(origin="/torques", name="torques (N m)"),
                    rrb.TimeSeriesView(origin="/velocities", name="velocities"),
                    rrb.TimeSeriesView(origin="/link", name="link"),
                ),
            ),
            collapse_panels=True,
        )
        self._rec.save(str(self.path), default_blueprint=blueprint)
        self._rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for j in JOINTS:
            self._rec.log(
                f"joints/{j}/position", rr.SeriesLines(names=["q", "setpoint"]), static=True
            )
            self._rec.log(
                f"joints/{j}/current", rr.SeriesLines(names=["applied", "drawn"]), static=True
            )
        for entity in ("torques", "velocities"):
            self._rec.log(entity, rr.SeriesLines(names=list(JOINTS)), static=True)
        self._rec.log(
            "link", rr.SeriesLines(names=["frames in", "bad frames", "frames out"]), static=True
        )
        meta = {
            "source": "reach-sim",
            "joint_names": list(JOINTS),
            "rate_hz": rate_hz,
            "speed": server.config.speed,
        }
        self._rec.log("run/metadata", rr.TextDocument(json.dumps(meta)), static=True)
        self._modes: tuple[Mode, ...] | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="reach-sim-recorder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        k, last_t = 0, -math.inf
        while not self._stop.is_set():
            if not self.server.wait_sim_time(k * self.period, timeout=0.2):
                if not self.server.running:
                    break
                continue
            sample = self.server.observe(_sample)
            if sample.t > last_t:  # the sim may not have stepped since the last look
                self.log(sample, k)
                last_t = sample.t
            k = max(k + 1, int(sample.t / self.period) + 1)

    def log(self, s: _Sample, k: int) -> None:
        rec = self._rec
        rec.set_time("arm_time", duration=s.t)
        rec.set_time("step", sequence=k)
        for i, j in enumerate(JOINTS):
            rec.log(f"joints/{j}/position", rr.Scalars([s.q[i], s.setpoint[i]]))
            rec.log(f"joints/{j}/current", rr.Scalars([s.applied_mA[i], s.drawn_mA[i]]))
        rec.log("torques", rr.Scalars(s.tau))
        rec.log("velocities", rr.Scalars(s.qdot))
        rec.log(
            "arm/skeleton", rr.LineStrips3D([s.skeleton], radii=0.01, colors=[(230, 150, 40, 255)])
        )
        stats = self.server.stats()
        rec.log(
            "link",
            rr.Scalars([float(stats.frames_in), float(stats.bad_total), float(stats.frames_out)]),
        )
        if s.modes != self._modes:
            names = ", ".join(f"{j}={m.name.lower()}" for j, m in zip(JOINTS, s.modes, strict=True))
            rec.log("events", rr.TextLog(f"modes: {names}", level="INFO"))
            self._modes = s.modes
        self.samples += 1
        if self.samples % self._flush_every == 0:
            rec.flush(timeout_sec=2.0)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._rec.flush(timeout_sec=5.0)
        self._rec.disconnect()
