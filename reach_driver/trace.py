"""The rows a control run collects, resampled onto its uniform tick grid (a `LoopTrace`),
and the torque model they are scored with.

On a real arm current x the joint's torque per amp (`protocol.alpha5.TORQUE_PER_AMP_NM`) is
the only torque estimate there is; the driver cannot import the simulator's motor model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from protocol.alpha5 import N_JOINTS, TORQUE_PER_AMP_NM
from reach_driver.records import LoopTrace

N = N_JOINTS
_TORQUE_PER_AMP = np.asarray(TORQUE_PER_AMP_NM, dtype=float)

#: The state that ended a run: loop time, q, qdot and the latest measured currents.
FinalState = tuple[float, np.ndarray, np.ndarray, np.ndarray]


def torque_from_current(current_mA: np.ndarray) -> np.ndarray:
    """Joint torque (N m) from motor current (mA), E D C B."""
    return np.asarray(current_mA, dtype=float) * 1e-3 * _TORQUE_PER_AMP


@dataclass
class TraceRows:
    """One row per state the controller acted on: loop time, q, qdot, measured current (NaN
    where not reported) and the command sent."""

    t: list[float] = field(default_factory=list)
    q: list[np.ndarray] = field(default_factory=list)
    qdot: list[np.ndarray] = field(default_factory=list)
    current: list[np.ndarray] = field(default_factory=list)
    command: list[np.ndarray] = field(default_factory=list)

    def add(
        self,
        t: float,
        q: np.ndarray,
        qdot: np.ndarray,
        current: np.ndarray,
        command: np.ndarray,
    ) -> None:
        self.t.append(t)
        self.q.append(q)
        self.qdot.append(qdot)
        self.current.append(current)
        self.command.append(command)

    def period_torque(self, measured: np.ndarray | None) -> np.ndarray:
        """Torque over the period ending now: the measured current where there is one, else
        the command held over that period."""
        held = self.command[-1] if self.command else np.zeros(N)
        if measured is None:
            return torque_from_current(held)
        return torque_from_current(np.where(np.isfinite(measured), measured, held))

    def resample(self, dt: float, final: FinalState | None) -> LoopTrace | None:
        """The rows (and the final state) on the uniform tick grid (see LoopTrace); None with
        under two states."""
        ts = list(self.t)
        qs, qds, cur = list(self.q), list(self.qdot), list(self.current)
        cmds = list(self.command)
        if final is not None:
            t, q, qdot, currents = final
            ts.append(t)
            qs.append(q)
            qds.append(qdot)
            cur.append(currents)
        if len(ts) < 2:
            return None
        k = np.rint(np.asarray(ts) / dt).astype(int)
        n = int(k[-1])
        grid = np.arange(n + 1)
        q_arr, qd_arr = np.asarray(qs), np.asarray(qds)
        q_out = np.column_stack([np.interp(grid, k, q_arr[:, j]) for j in range(N)])
        qd_out = np.column_stack([np.interp(grid, k, qd_arr[:, j]) for j in range(N)])
        # command row i = what was held over the period ending at sample i
        cmd_rows = np.zeros((n + 1, N))
        cur_rows = np.full((n + 1, N), np.nan)
        held = np.zeros(N)
        by_tick = {int(kk): i for i, kk in enumerate(k)}
        for i in range(n + 1):
            if i > 0 and (i - 1) in by_tick and by_tick[i - 1] < len(cmds):
                held = cmds[by_tick[i - 1]]
            cmd_rows[i] = held if i > 0 else 0.0
            if i in by_tick:
                cur_rows[i] = cur[by_tick[i]]
        measured = np.where(np.isfinite(cur_rows), cur_rows, cmd_rows)
        measured[0] = np.where(np.isfinite(cur_rows[0]), cur_rows[0], 0.0)
        return LoopTrace(
            dt=dt,
            t=grid * dt,
            q=q_out,
            qdot=qd_out,
            command_mA=cmd_rows,
            current_mA=cur_rows,
            torque_Nm=torque_from_current(measured),
            filled=int(n + 1 - len(set(k.tolist()))),
        )
