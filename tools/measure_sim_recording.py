#!/usr/bin/env python3
"""Bytes per minute of `reach-sim --record`, with the arm idle and with it moving.

Runs the simulator faster than real time (`--speed`) with a SimRecorder attached, for
`--seconds` of sim time idle (no client) and then the same time moving (position commands to
D and C alternating every 1.5 s over the pty), and prints the recording's growth per minute of
sim time in each phase. `rate_hz` is the recorder's full rate (reach-sim's `--record-rate`).
"""

from __future__ import annotations

import argparse
import inspect
import json
import tempfile
import time
from pathlib import Path

import serial

from protocol import DeviceID, commands
from reach_sim_bridge.emulator.recording import SimRecorder
from reach_sim_bridge.emulator.server import SimConfig, SimServer


def _bytes_on_disk(path: Path) -> int:
    """The recording and any rotated parts beside it (name.1.rrd, name.2.rrd, ...)."""
    return sum(p.stat().st_size for p in path.parent.glob(f"{path.stem}*{path.suffix}"))


def _flush(recorder: SimRecorder) -> None:
    flush = getattr(recorder, "flush", None)
    if flush is not None:
        flush()
    else:  # the recorder before it had one
        assert recorder._rec is not None  # it records to a file
        recorder._rec.flush(timeout_sec=5.0)


def measure(seconds: float, speed: float, rate_hz: float) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sim.rrd"
        with SimServer(SimConfig(speed=speed, start=(3.0, 1.5, 1.5, 1.5))) as srv:
            kwargs: dict[str, object] = {"rate_hz": rate_hz}
            if "max_bytes" in inspect.signature(SimRecorder).parameters:
                kwargs["max_bytes"] = None  # growth, not the cap, is measured here
            recorder = SimRecorder(srv, path, **kwargs)  # type: ignore[arg-type]
            recorder.start()
            assert srv.pty_path is not None
            with serial.Serial(srv.pty_path, 115200, timeout=0.05) as port:
                # Settle: hold the start pose in position mode, then measure idle.
                for dev, angle in ((DeviceID.D, 1.5), (DeviceID.C, 1.5)):
                    port.write(commands.position(dev, angle).encode())
                srv.wait_sim_time(srv.sim_time + 3.0, timeout=120)
                _flush(recorder)
                t0, b0 = srv.sim_time, _bytes_on_disk(path)
                srv.wait_sim_time(t0 + seconds, timeout=600)
                _flush(recorder)
                t1, b1 = srv.sim_time, _bytes_on_disk(path)
                k = 0
                while srv.sim_time < t1 + seconds:
                    a = 1.2 if k % 2 else 1.9
                    port.write(commands.position(DeviceID.D, a).encode())
                    port.write(commands.position(DeviceID.C, 3.2 - a).encode())
                    srv.wait_sim_time(srv.sim_time + 1.5, timeout=120)
                    k += 1
                _flush(recorder)
                t2, b2 = srv.sim_time, _bytes_on_disk(path)
            recorder.stop()
    return {
        "idle_bytes_per_min": (b1 - b0) / (t1 - t0) * 60.0,
        "moving_bytes_per_min": (b2 - b1) / (t2 - t1) * 60.0,
        "idle_MB_per_hour": (b1 - b0) / (t1 - t0) * 3600.0 / 1e6,
        "moving_MB_per_hour": (b2 - b1) / (t2 - t1) * 3600.0 / 1e6,
        "sim_seconds_per_phase": seconds,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--seconds", type=float, default=30.0, help="sim seconds per phase")
    p.add_argument("--speed", type=float, default=4.0, help="sim seconds per wall second")
    p.add_argument("--rate", type=float, default=50.0, help="recorder full rate (Hz)")
    args = p.parse_args()
    started = time.monotonic()
    result = measure(args.seconds, args.speed, args.rate)
    result["wall_s"] = time.monotonic() - started
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
