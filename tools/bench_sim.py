"""Benchmarks of the virtual arm; prints figures measured in this process.

Physics section (reach_sim_bridge.model.step_speed): how fast ``Alpha5Arm.step`` runs the way
the RL environment calls it (random currents held for 25 physics steps of 2 ms, i.e. 20 Hz
control, episodes of 20 s), with and without fluid drag, against the same motor law evaluated
once per control period with the period run by one ``mj_step(m, d, nstep)`` call (the cost of
the per-step clamp), and against the naive alternative (motor torque computed explicitly each
step in numpy, which also chatters at the back-EMF limit).

The machine is shared, so rates are per CPU second of this process (``process_time``: the
rate on one dedicated core), each the best of ``--repeats`` windows, and ratios are taken
between runs in this process.

Each section is a function returning ``BenchResult`` rows, registered in ``SECTIONS``; add
new sections (e.g. pty round-trip latency) the same way.

    .venv/bin/python tools/bench_sim.py            # all sections
    .venv/bin/python tools/bench_sim.py --only physics --seconds 5
"""

from __future__ import annotations

import argparse
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable

import numpy as np
import serial

from protocol import DeviceID, PacketDecoder, PacketID, commands
from reach_sim_bridge.emulator.server import INPUT_UNITS_PER_S
from reach_sim_bridge.model.step_speed import BenchResult, physics_rows


def physics_section(args: argparse.Namespace) -> list[BenchResult]:
    """Alpha5Arm.step against its baseline and the rejected designs
    (reach_sim_bridge.model.step_speed)."""
    return physics_rows(args.seconds, args.repeats, args.substeps)


# -- pty round trip (reach_sim_bridge.emulator.server)
# -------------------------------------------------
# The simulator runs as `reach-sim` in its own process, as users run it; the baseline is a
# bare echo server on a raw pty (and on UDP) in its own process, so the ratio is the cost of
# decoding, the firmware and the paced physics loop on top of the OS round trip.
_ECHO_SERVER = """
import os, select, socket, sys, tty
master, slave = os.openpty()
tty.setraw(slave)
udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
udp.bind(("127.0.0.1", 0))
print("pty", os.ttyname(slave))
print("udp", "127.0.0.1:%d" % udp.getsockname()[1], flush=True)
while True:
    for fd in select.select([master, udp, sys.stdin], [], [])[0]:
        if fd is master:
            os.write(master, os.read(master, 4096))
        elif fd is udp:
            data, peer = udp.recvfrom(65535)
            udp.sendto(data, peer)
        else:
            sys.exit(0)
"""


def _spawn(argv: list[str]) -> tuple[subprocess.Popen[str], dict[str, str]]:
    proc = subprocess.Popen(
        argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    assert proc.stdout is not None
    lines: dict[str, str] = {}
    while not {"pty", "udp"} <= lines.keys():
        line = proc.stdout.readline()
        if not line:
            raise RuntimeError(f"{argv[:3]} exited before printing its addresses")
        key, _, value = line.strip().partition(" ")
        lines[key] = value
    return proc, lines


def _stop(proc: subprocess.Popen[str]) -> None:
    proc.send_signal(signal.SIGTERM)
    if proc.stdin is not None:
        proc.stdin.close()  # the echo server exits on EOF
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _round_trips(
    exchange: Callable[[], None], seconds: float, limit: int = 20000, spacing_s: float = 0.0
) -> np.ndarray:
    """Seconds per exchange for `seconds` of wall time (after a warm-up), each started at
    least `spacing_s` after the one before (back to back with 0)."""
    for _ in range(20):
        exchange()
        time.sleep(spacing_s)
    samples: list[float] = []
    end = time.perf_counter() + seconds
    next_t = time.perf_counter()
    while next_t < end and len(samples) < limit:
        wait = next_t - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
        t0 = time.perf_counter()
        exchange()
        samples.append(time.perf_counter() - t0)
        next_t = t0 + spacing_s
    return np.array(samples)


def _serial_exchange(
    path: str, request: bytes, replies: int
) -> tuple[Callable[[], None], Callable[[], None]]:
    port = serial.Serial(path, 115200, timeout=1.0)
    decoder = PacketDecoder()

    def exchange() -> None:
        port.write(request)
        got = 0
        while got < replies:
            chunk = port.read(port.in_waiting or 1)
            if not chunk:
                raise TimeoutError(f"no reply on {path} within 1 s")
            got += len(decoder.feed(chunk))

    return exchange, port.close


def _udp_exchange(
    address: str, request: bytes, replies: int
) -> tuple[Callable[[], None], Callable[[], None]]:
    host, _, port = address.rpartition(":")
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(1.0)
    sock.connect((host, int(port)))
    decoder = PacketDecoder()

    def exchange() -> None:
        sock.send(request)
        got = 0
        while got < replies:
            got += len(decoder.feed(sock.recv(65535)))

    return exchange, sock.close


def _latency_row(name: str, samples: np.ndarray, baseline: np.ndarray | None) -> BenchResult:
    p50, p99 = np.percentile(samples, [50, 99]) * 1e6
    extra = {"p50_us": f"{p50:,.0f}", "p99_us": f"{p99:,.0f}", "n": str(len(samples))}
    if baseline is not None:
        extra["p50_vs_echo"] = f"{p50 / (np.percentile(baseline, 50) * 1e6):.1f}x"
    return BenchResult(name, 1.0 / samples.mean(), "round trips/s", extra)


def pty_section(args: argparse.Namespace) -> list[BenchResult]:
    """REQUEST round-trip latency through `reach-sim` (real-time pacing) over the pty and UDP,
    against a bare echo of the same request bytes on a raw pty / UDP socket."""
    one = commands.request(DeviceID.E, [PacketID.POSITION]).encode()
    joints = commands.request(DeviceID.BROADCAST, [PacketID.POSITION, PacketID.VELOCITY]).encode()
    window = args.seconds / 2
    echo, echo_at = _spawn([sys.executable, "-c", _ECHO_SERVER])
    try:
        pty_echo, close = _serial_exchange(echo_at["pty"], one, 1)
        base_pty = _round_trips(pty_echo, window)
        close()
        udp_echo, close = _udp_exchange(echo_at["udp"], one, 1)
        base_udp = _round_trips(udp_echo, window)
        close()
    finally:
        _stop(echo)
    results = [
        _latency_row("baseline: raw pty echo (7 bytes)", base_pty, None),
        _latency_row("baseline: UDP echo (7 bytes)", base_udp, None),
    ]
    cases = [
        ([], "pty", one, 1, base_pty, "reach-sim pty: REQUEST POSITION of E"),
        ([], "pty", joints, 10, None, "reach-sim pty: broadcast POSITION+VELOCITY"),
        (["--udp", "127.0.0.1:0"], "udp", one, 1, base_udp, "reach-sim UDP: REQUEST POSITION"),
        (["--baud", "115200"], "pty", one, 1, base_pty, "reach-sim pty at 115200 baud"),
    ]
    for extra_args, kind, request, replies, baseline, name in cases:
        argv = [sys.executable, "-m", "reach_sim_bridge.cli", "--stats-interval", "0", *extra_args]
        if "--udp" not in argv:
            argv += ["--udp", "127.0.0.1:0"]  # _spawn waits for both addresses
        sim, at = _spawn(argv)
        try:
            opener = _serial_exchange if kind == "pty" else _udp_exchange
            exchange, close = opener(at[kind], request, replies)
            # reach-sim's flood budget (INPUT_UNITS_PER_S: a frame read or a reply made is a
            # unit) drops what comes faster; back to back, a request and its reply every
            # 26 us would exceed it, so exchanges are spaced to use half of it
            spacing = 2 * (1 + replies) / INPUT_UNITS_PER_S
            samples = _round_trips(exchange, window, spacing_s=spacing)
            close()
        finally:
            _stop(sim)
        row = _latency_row(name, samples, baseline)
        if "--baud" in extra_args:
            wire = (len(request) + 10) * 10 / 115200 * 1e6  # request + 10-byte reply, 8N1
            row.extra["wire_time_us"] = f"{wire:,.0f}"
        results.append(row)
    return results


SECTIONS: dict[str, Callable[[argparse.Namespace], list[BenchResult]]] = {
    "physics": physics_section,
    "pty": pty_section,
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Measure the virtual arm's speed: physics steps per second and real-time "
        "factor of Alpha5Arm.step as the RL environment calls it (20 Hz control, 25 steps "
        "of 2 ms), with and without fluid drag, against a once-per-period clamp in the same "
        "process. Rates are per CPU second (one core), best of --repeats windows.",
    )
    parser.add_argument(
        "--only",
        choices=sorted(SECTIONS),
        action="append",
        help="run only this section (repeatable); default: all",
    )
    parser.add_argument(
        "--seconds", type=float, default=6.0, help="CPU time per measurement (default 6)"
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=3,
        help="windows per measurement, best one reported (default 3)",
    )
    parser.add_argument(
        "--substeps",
        type=int,
        default=25,
        help="physics steps per arm.step call (default 25 = 20 Hz at 2 ms)",
    )
    args = parser.parse_args(argv)
    if not args.seconds > 0 or args.substeps < 1 or args.repeats < 1:
        parser.error("--seconds must be > 0, --substeps and --repeats >= 1")
    for name in args.only or list(SECTIONS):
        print(f"== {name}")
        for result in SECTIONS[name](args):
            print(result.line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
