"""The rows a control run collects, resampled onto its uniform tick grid (a `LoopTrace`),
and the torque model they are scored with.

On a real arm current x the joint's torque per amp (`ArmModel.torque_per_amp_nm`, the Alpha
5's by default) is the only torque estimate there is; the driver cannot import the
simulator's motor model.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from protocol.models import ALPHA5
from reach_driver.records import LoopTrace

#: The state that ended a run: loop time, q, qdot and the latest measured currents.
FinalState = tuple[float, np.ndarray, np.ndarray, np.ndarray]


def torque_from_current(
    current_mA: np.ndarray, torque_per_amp_nm: Sequence[float] = ALPHA5.torque_per_amp_nm
) -> np.ndarray:
    """Joint torque (N m) from motor current (mA), in the joints' order of `torque_per_amp_nm`
    (the Alpha 5's E D C B by default)."""
    return np.asarray(current_mA, dtype=float) * 1e-3 * np.asarray(torque_per_amp_nm, float)


@dataclass
class TraceRows:
    """One row per state the controller acted on: loop time, q, qdot, measured current (NaN
    where not reported) and the command sent; torque from current by `torque_per_amp_nm`."""

    torque_per_amp_nm: Sequence[float] = ALPHA5.torque_per_amp_nm
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
        held = self.command[-1] if self.command else np.zeros(len(self.torque_per_amp_nm))
        if measured is None:
            return torque_from_current(held, self.torque_per_amp_nm)
        measured = np.where(np.isfinite(measured), measured, held)
        return torque_from_current(measured, self.torque_per_amp_nm)

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
        joints = len(self.torque_per_amp_nm)
        k = np.rint(np.asarray(ts) / dt).astype(int)
        n = int(k[-1])
        grid = np.arange(n + 1)
        q_arr, qd_arr = np.asarray(qs), np.asarray(qds)
        q_out = np.column_stack([np.interp(grid, k, q_arr[:, j]) for j in range(joints)])
        qd_out = np.column_stack([np.interp(grid, k, qd_arr[:, j]) for j in range(joints)])
        # command row i = what was held over the period ending at sample i
        cmd_rows = np.zeros((n + 1, joints))
        cur_rows = np.full((n + 1, joints), np.nan)
        held = np.zeros(joints)
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
            torque_Nm=torque_from_current(measured, self.torque_per_amp_nm),
            filled=int(n + 1 - len(set(k.tolist()))),
        )
