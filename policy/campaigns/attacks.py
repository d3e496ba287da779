"""Attacks on the stack, as an adversarial tester would make them: fuzzed and flooded input to
the codec and the virtual arm, strangers on its UDP port, bad commands, a silent controller and a
lying arm. Each is bounded in count (times `scale`) and time, stops by itself and keeps all
traffic on loopback (a virtual arm in this process, on a pty and 127.0.0.1); each returns an
`Outcome` saying whether the stack held. tools/attack.py runs them and prints the table.
"""

from __future__ import annotations

import json
import math
import os
import random
import resource
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from protocol import DeviceID, Mode, Packet, PacketDecoder, PacketID, commands, encode_packet
from protocol.payload import pack_floats
from reach_driver import ArmClient, DriverError, LimitKind, SafetyConfig, open_transport
from reach_sim_bridge.emulator.faults import StuckReading
from reach_sim_bridge.emulator.firmware import Firmware
from reach_sim_bridge.emulator.server import SimConfig, SimServer
from reach_sim_bridge.model.arm import Alpha5Arm

E, D, C, B = DeviceID.E, DeviceID.D, DeviceID.C, DeviceID.B


@dataclass
class Outcome:
    """One attack's row of the table: what was sent, what came of it, whether the stack held."""

    attack: str
    count: str
    result: str
    held: bool


def _rss_mb() -> float:
    """Resident memory of this process now (MB), from /proc where there is one."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _wait(predicate: Callable[[], object], timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.005)
    return bool(predicate())


def _server(tmp: str, **kwargs: object) -> SimServer:
    server = SimServer(
        SimConfig(link=os.path.join(tmp, "arm"), udp=("127.0.0.1", 0), **kwargs)  # type: ignore[arg-type]
    )
    server.start()
    return server


# -- the attacks ----------------------------------------------------------------------------


def codec_fuzz(scale: float, tmp: str) -> Outcome:
    """Mutated valid frames and random bytes into the stream decoder: no crash, and every byte
    accounted for (a good frame, discarded, or pending)."""
    rng = random.Random(2026)
    runs = max(1000, int(200_000 * scale))
    valid = [
        commands.position(E, 1.5).encode(),
        commands.request(D, [PacketID.POSITION, PacketID.VELOCITY]).encode(),
        commands.current(B, -120.0).encode(),
        encode_packet(C, PacketID.HARDWARE_STATUS, bytes(4)),
    ]
    decoder = PacketDecoder()
    crashes = good_bytes = 0
    for _ in range(runs):
        frame = bytearray(rng.choice(valid))
        kind = rng.random()
        if kind < 0.4:
            frame[rng.randrange(len(frame))] = rng.randrange(256)
        elif kind < 0.6:
            del frame[rng.randrange(len(frame)) :]
        elif kind < 0.8:
            frame = bytearray(rng.randbytes(rng.randrange(1, 300)))
        try:
            # A good frame re-encodes to the bytes it came in (COBS and CRC are canonical).
            good_bytes += sum(len(p.encode()) for p in decoder.feed(bytes(frame)))
        except Exception:  # noqa: BLE001 - any escape is the finding
            crashes += 1
    s = decoder.stats
    accounted = s.bytes_received == good_bytes + s.bytes_discarded + decoder.pending_bytes
    held = crashes == 0 and accounted
    return Outcome(
        "codec-fuzz",
        f"{runs:,} frames",
        f"{s.good_frames:,} good, {s.bad_total:,} bad, {crashes} crashes, bytes accounted: "
        f"{accounted}",
        held,
    )


def junk_flood(scale: float, tmp: str) -> Outcome:
    """Undelimited junk at the virtual arm's pty: memory stays flat, the arm still answers."""
    megabytes = max(1, int(50 * scale))
    server = _server(tmp)
    try:
        fd = os.open(str(server.link), os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        chunk = bytes(random.Random(1).randrange(1, 256) for _ in range(65536))  # no 0x00
        before = _rss_mb()
        sent, end = 0, time.monotonic() + 30.0
        while sent < megabytes * 2**20 and time.monotonic() < end:
            try:
                sent += os.write(fd, chunk)
            except BlockingIOError:
                time.sleep(0.001)
            try:
                while os.read(fd, 65536):
                    pass
            except BlockingIOError:
                pass
        os.close(fd)
        grown = _rss_mb() - before
        with ArmClient(open_transport(str(server.link))) as arm:
            answered = bool(arm.request(E, [PacketID.POSITION]))
    finally:
        server.stop()
    held = answered and grown < 50.0
    return Outcome(
        "junk-flood",
        f"{sent / 2**20:.0f} MB",
        f"memory +{grown:.1f} MB, answered afterwards: {answered}",
        held,
    )


def udp_stranger(scale: float, tmp: str) -> Outcome:
    """Garbage datagrams from another local port must not take the UDP heartbeat."""
    count = max(10, int(2000 * scale))
    server = _server(tmp)
    assert server.udp_address is not None
    host, port = server.udp_address
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        peer.settimeout(0.5)
        stranger.setblocking(False)
        peer.sendto(commands.heartbeat_set(E, [PacketID.POSITION]).encode(), (host, port))
        peer.sendto(commands.heartbeat_frequency(E, 50).encode(), (host, port))
        for _ in range(count):
            stranger.sendto(b"\x13\x37\x42", (host, port))
        got = _count_frames(peer, 1.0)
        stolen = 0
        try:
            while True:
                stolen += len(stranger.recv(65536))
        except BlockingIOError:
            pass
        peer.sendto(commands.heartbeat_frequency(E, 0).encode(), (host, port))
    finally:
        peer.close()
        stranger.close()
        server.stop()
    held = got >= 20 and stolen == 0
    return Outcome(
        "udp-stranger",
        f"{count:,} datagrams",
        f"peer got {got} heartbeat frames in 1 s, stranger got {stolen} bytes",
        held,
    )


def _count_frames(sock: socket.socket, seconds: float) -> int:
    decoder, frames, end = PacketDecoder(), 0, time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            frames += len(decoder.feed(sock.recv(65536)))
        except TimeoutError:
            break
    return frames


def request_flood(scale: float, tmp: str) -> Outcome:
    """Broadcast requests as fast as loopback UDP carries them: the physics keeps real time."""
    seconds = max(1.0, 4.0 * scale)
    server = _server(tmp)
    assert server.udp_address is not None
    host, port = server.udp_address
    ask = commands.request(DeviceID.BROADCAST, [PacketID.POSITION, PacketID.VELOCITY]).encode()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setblocking(False)
    sent = 0
    try:
        t0, sim0 = time.monotonic(), server.sim_time
        while time.monotonic() - t0 < seconds:
            try:
                sock.sendto(ask * 50, (host, port))
                sent += 50
            except BlockingIOError:
                time.sleep(0.0005)
            try:
                while sock.recv(65536):
                    pass
            except BlockingIOError:
                pass
        ratio = (server.sim_time - sim0) / (time.monotonic() - t0)
        stats = server.stats()
    finally:
        sock.close()
        server.stop()
    # Loopback drops what the socket buffer cannot hold without telling the sender, so what
    # was offered and what the arm read differ.
    return Outcome(
        "request-flood",
        f"{sent:,} requests offered in {seconds:.0f} s",
        f"{stats.datagrams_in:,} datagrams read, {stats.input_dropped_bytes:,} bytes dropped "
        f"by the input budget; sim time / wall time {ratio:.2f}",
        ratio >= 0.8,
    )


def bad_commands(scale: float, tmp: str) -> Outcome:
    """NaN, Inf and out-of-limit commands are refused before the wire."""
    server = _server(tmp)
    refused = total = 0
    try:
        with ArmClient(open_transport(str(server.link))) as arm:
            frames_before = server.stats().frames_in
            for value in (math.nan, math.inf, -math.inf, 1e30, 5000.0):
                for send in (
                    lambda v: arm.command_current(E, v),
                    lambda v: arm.command_position(D, v),
                    lambda v: arm.command_velocity(C, v),
                ):
                    total += 1
                    try:
                        send(value)
                    except (DriverError, ValueError):
                        refused += 1
            time.sleep(0.2)
            reached = server.stats().frames_in - frames_before
    finally:
        server.stop()
    # A current above the limit may be clamped rather than refused; what matters is that no
    # non-finite value and no out-of-envelope position reached the arm.
    q = server.snapshot().q
    inside = bool(0.0 <= q[1] <= 3.5)
    return Outcome(
        "bad-commands",
        f"{total} commands",
        f"{refused} refused, {reached} frames reached the arm, D stayed inside: {inside}",
        refused >= 12 and inside,
    )


def watchdog(scale: float, tmp: str) -> Outcome:
    """A controller that stops sending: the watchdog puts the arm in zero velocity."""
    server = _server(tmp)
    try:
        with ArmClient(
            open_transport(str(server.link)), safety=SafetyConfig(watchdog_s=0.2)
        ) as arm:
            arm.stream((PacketID.POSITION,), 50, [C])
            _wait(lambda: arm.joint(C).position is not None, 10.0)
            arm.command_current(C, 30.0)
            t0 = time.monotonic()
            stopped = _wait(lambda: server.firmware.mode(int(C)) == Mode.ZERO_VELOCITY, 3.0)
            trip_s = time.monotonic() - t0
    finally:
        server.stop()
    return Outcome(
        "watchdog",
        "1 silent controller",
        f"zero velocity after {trip_s:.2f} s (watchdog 0.20 s)",
        stopped and trip_s < 1.0,
    )


def hostile_arm(scale: float, tmp: str) -> Outcome:
    """A fake arm on loop:// (the driver reads back what it writes) reports absurd limits
    unasked, then the driver is asked for motion the gate must refuse: nothing may reach the
    wire, and the factory envelope must stay in force."""
    arm = ArmClient(open_transport("loop://"), safety=SafetyConfig(watchdog_s=None))
    arm.start(discover=False, read_limits=False)
    try:
        lies = [
            encode_packet(E, PacketID.POSITION_LIMITS, pack_floats(1e6, -1e6)),
            encode_packet(D, PacketID.CURRENT_LIMITS, pack_floats(math.inf, -math.inf)),
            encode_packet(C, PacketID.VELOCITY_LIMITS, pack_floats(1e30, -1e30)),
        ]
        arm.transport.write_frames(lies)
        _wait(lambda: arm.joint(C).velocity_limits is not None, 2.0)
        before = arm.transport.stats.bytes_out
        motion = [
            lambda: arm.command_position(E, 500.0),
            lambda: arm.command_current(D, 1e5),
            lambda: arm.send(encode_packet_as(E, PacketID.RELATIVE_POSITION, 2.0)),
            lambda: arm.send(encode_packet_as(DeviceID.BROADCAST, PacketID.POSITION, 1.0)),
            lambda: arm.send(encode_packet_as(0x09, PacketID.CURRENT, 100.0)),
            lambda: arm.send(encode_packet_as(E, PacketID.KM_END_VEL, 10.0, 0, 0, 0, 0, 0)),
            lambda: arm.write_limits(E, LimitKind.CURRENT, math.inf, -math.inf),
        ]
        refused = 0
        for attempt in motion:
            try:
                attempt()
            except (DriverError, ValueError):
                refused += 1
        leaked = arm.transport.stats.bytes_out - before
        lim = arm.guard.limit(E, LimitKind.POSITION)
        kept = abs(lim.low - 0.0175) < 1e-6 and abs(lim.high - 6.143) < 1e-6  # the factory's
        rejected = arm.stats.limits_rejected
    finally:
        arm.close(safe=False)
    return Outcome(
        "hostile-arm",
        f"{len(lies)} lies, {len(motion)} motion packets",
        f"{rejected} limit reports rejected, {refused} packets refused, {leaked} bytes "
        f"reached the wire, E's bound kept at [{lim.low:g}, {lim.high:g}]",
        rejected == len(lies) and refused == len(motion) and leaked == 0 and kept,
    )


# -- the ways a move or run ends ---------------------------------------------------------------

REPO = Path(__file__).resolve().parents[2]
JOINT_IDS = (5, 4, 3, 2)


def driver_process(*argv: str) -> subprocess.Popen[str]:
    """`reach-driver ARGV` from this tree in a child, Ctrl-C at its default (as a shell in the
    foreground starts it)."""
    return subprocess.Popen(
        [sys.executable, "-m", "reach_driver", *argv],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def finish_process(proc: subprocess.Popen[str]) -> tuple[str, str]:
    try:
        return proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()


def _safe(server: SimServer) -> bool:
    return all(server.firmware.mode(d) == Mode.ZERO_VELOCITY for d in JOINT_IDS)


def _pushing_run(port: str, server: SimServer, *options: str) -> list[str]:
    """A PID run to E 1.5 rad away (at most 6.0): E saturates at its 600 mA for seconds."""
    q = server.snapshot().q
    target = [min(q[0] + 1.5, 6.0), q[1] + 0.2, q[2] + 0.2, q[3] + 0.2]
    run = ["--port", port, "--watchdog", "1", *options, "run", "--controller", "pid"]
    return run + ["--target", *map(str, target), "--seconds", "600"]


CONFIRMED = "arm left in zero_velocity (confirmed by the arm)"


def exit_signals(scale: float, tmp: str) -> Outcome:
    """SIGHUP (an ssh drop), SIGQUIT, SIGTERM and SIGINT at a `run` pushing E at its current
    limit: each must end with the arm confirmed in zero velocity, the summary, 128 + signal."""
    server = _server(tmp)
    said = []
    held = True
    try:
        for sig in (signal.SIGHUP, signal.SIGQUIT, signal.SIGTERM, signal.SIGINT):
            proc = driver_process(*_pushing_run(str(server.link), server))
            try:
                if _wait(lambda: server.firmware.mode(5) == Mode.CURRENT, 60.0):
                    proc.send_signal(sig)
            finally:
                out, err = finish_process(proc)
            ok = _safe(server) and proc.returncode == 128 + sig and CONFIRMED in out
            held &= ok and "Traceback" not in err
            said.append(f"{sig.name} {proc.returncode}{'' if ok else ' NOT SAFE'}")
    finally:
        server.stop()
    return Outcome(
        "exit-signals",
        "4 signals to a run at 600 mA",
        f"exit {', '.join(said)}; each with the summary and '{CONFIRMED}'",
        held,
    )


class HangingLink:
    """A UDP relay between a driver and an arm that can hang: while `hang` is set every
    datagram, either way, is dropped (an arm whose network side stops answering). Counts the
    ZERO_VELOCITY mode commands to E it drops."""

    def __init__(self, arm: tuple[str, int]) -> None:
        self.arm = arm
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.bind(("127.0.0.1", 0))
        self.hang = threading.Event()
        self.dropped_safe = 0
        self._client: tuple[str, int] | None = None
        self._stop = threading.Event()
        self._decoder = PacketDecoder()
        self._threads = [
            threading.Thread(target=self._pump, args=(self.front, True), daemon=True),
            threading.Thread(target=self._pump, args=(self.back, False), daemon=True),
        ]
        for t in self._threads:
            t.start()

    @property
    def url(self) -> str:
        host, port = self.front.getsockname()
        return f"udp://{host}:{port}"

    def _pump(self, sock: socket.socket, from_driver: bool) -> None:
        sock.settimeout(0.05)
        while not self._stop.is_set():
            try:
                data, addr = sock.recvfrom(65536)
            except OSError:  # a timeout too
                continue
            if from_driver:
                self._client = addr
                if self.hang.is_set():
                    for packet in self._decoder.feed(data):
                        if (
                            packet.packet_id == PacketID.MODE
                            and packet.device_id == E
                            and packet.data[:1] == bytes([Mode.ZERO_VELOCITY])
                        ):
                            self.dropped_safe += 1
                    continue
                self.back.sendto(data, self.arm)
            elif not self.hang.is_set() and self._client is not None:
                self.front.sendto(data, self._client)

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join()
        self.front.close()
        self.back.close()


def hang_at_interrupt(scale: float, tmp: str) -> Outcome:
    """Ctrl-C while the arm's network side hangs: the driver must keep sending the safe mode
    until the arm, answering again, confirms it, and say so only then."""
    server = _server(tmp)
    assert server.udp_address is not None
    link = HangingLink(server.udp_address)
    try:
        still_pushing = False
        proc = driver_process(*_pushing_run(link.url, server, "--safe-wait", "60"))
        try:
            if _wait(lambda: server.firmware.mode(5) == Mode.CURRENT, 60.0):
                link.hang.set()
                proc.send_signal(signal.SIGINT)
                # the hang lasts until the safe mode was lost twice, or 5 s: a link the
                # driver has given up as down gets the owed safe mode on reconnect instead
                _wait(lambda: link.dropped_safe >= 2 or proc.poll() is not None, 5.0)
                still_pushing = server.firmware.mode(5) == Mode.CURRENT
                link.hang.clear()
        finally:
            out, err = finish_process(proc)
        resent = link.dropped_safe
    finally:
        link.close()
        server.stop()
    safe = _safe(server)
    return Outcome(
        "hang-at-interrupt",
        "1 Ctrl-C into a hung link",
        f"zero_velocity lost {resent} times in the hang and resent; once the arm answered: "
        f"{'confirmed' if 'confirmed by the arm' in err else 'NOT confirmed'}, exit "
        f"{proc.returncode}",
        resent >= 1
        and still_pushing
        and safe
        and "confirmed by the arm" in err
        and proc.returncode == 130,
    )


def move_timeout(scale: float, tmp: str) -> Outcome:
    """`move --timeout 1` to a target 3 s away: the joints must stop where they are."""
    server = _server(tmp)
    try:
        target = server.snapshot().q + [-1.5, 0.0, 0.0, 0.0]
        proc = driver_process(
            "--port", str(server.link), "move", *map(str, target), "--timeout", "1"
        )
        out, err = finish_process(proc)
        safe = _safe(server)
        e0 = server.snapshot().q[0]
        server.wait_sim_time(server.sim_time + 1.0, timeout=30.0)
        drift = abs(server.snapshot().q[0] - e0)
    finally:
        server.stop()
    return Outcome(
        "move-timeout",
        "1 move cut short",
        f"exit {proc.returncode}, joints {'in zero_velocity' if safe else 'NOT safe'}, E moved "
        f"{drift * 1e3:.1f} mrad in the next second",
        proc.returncode == 1 and safe and drift < 0.02 and CONFIRMED in out,
    )


TOOK_THE_STREAM = "another client on this arm's UDP port took the stream"


def ended(proc: subprocess.Popen[str]) -> Callable[[], bool]:
    return lambda: proc.poll() is not None


def _last_error(text: str) -> str:
    """The line a run ended on (its "run failed" or watchdog line), for an outcome's text."""
    lines = [ln for ln in text.splitlines() if "failed" in ln or "watchdog" in ln]
    return lines[-1][:160] if lines else "no error line"


def udp_second_client(scale: float, tmp: str) -> Outcome:
    """`reach-driver info` from a second client while a `run` drives the arm over UDP: the
    arm streams to the last host that wrote to it, so `info` takes the run's heartbeat. The
    run must name that (not blame its controller or the link) and leave the arm safe. With
    --watchdog 1 the run's keepalive (after 0.25 s of silence) usually takes the stream back
    before anything trips, and the run goes on (ended here by Ctrl-C); on a loaded host the
    keepalive can come too late, and then the trip must name the other client as above. Both
    are right; what must never happen is a trip blamed on the controller or an unsafe arm."""
    server = _server(tmp)
    assert server.udp_address is not None
    url = f"udp://127.0.0.1:{server.udp_address[1]}"
    said, held = [], True
    try:
        for watchdog_s in ("0.2", "1"):
            argv = _pushing_run(url, server)
            argv[argv.index("--watchdog") + 1] = watchdog_s
            proc = driver_process(*argv)
            try:
                if _wait(lambda: server.firmware.mode(5) == Mode.CURRENT, 60.0):
                    for _ in range(1 if watchdog_s == "1" else 5):
                        # A run's command in flight may land after info's last request and
                        # take the stream back (the run goes on): then another info.
                        finish_process(driver_process("--port", url, "info"))
                        if watchdog_s == "1" or _wait(ended(proc), 2.0):
                            break
                    if watchdog_s == "1":
                        server.wait_sim_time(server.sim_time + 1.0, timeout=30.0)
                        went_on = proc.poll() is None and server.firmware.mode(5) == Mode.CURRENT
                        proc.send_signal(signal.SIGINT)
            finally:
                out, err = finish_process(proc)
            safe = _safe(server) and CONFIRMED in out and "Traceback" not in err
            # ticks lost whole while the stream was elsewhere are a gap the checks allow for:
            # neither the stream-rate nor the plausibility check may end the run on them
            named = TOOK_THE_STREAM in out + err
            if watchdog_s == "1":
                ok = safe and (
                    (went_on and proc.returncode == 130) or (named and proc.returncode == 1)
                )
                said.append(
                    "--watchdog 1: "
                    + ("went on" if went_on else "tripped, " + ("named" if named else "NOT named"))
                    + ("" if named or went_on else f" ({_last_error(out + err)})")
                    + f", exit {proc.returncode}"
                )
            else:
                ok = named and proc.returncode == 1 and safe
                how = "the other client named" if named else "NOT named: " + _last_error(out + err)
                said.append(
                    f"--watchdog 0.2: exit {proc.returncode}, {how}, "
                    f"{'safe (confirmed)' if safe else 'NOT safe'}"
                )
            held &= ok
    finally:
        server.stop()
    return Outcome(
        "udp-second-client",
        "2 runs, info from a second client",
        "; ".join(said) + f" ('{TOOK_THE_STREAM}', '{CONFIRMED}')",
        held,
    )


def lie_about_velocity(server: SimServer, value: float) -> None:
    """While E is in current mode (a controller has acted), `server`'s E reports `value` as
    its velocity: a sensor or firmware fault the emulator has no switch for."""
    firmware = server.firmware
    honest = firmware._noisy_velocity

    def lying(d: Any) -> float:
        if d.spec.device_id == E and firmware.mode(int(E)) == Mode.CURRENT:
            return value
        return honest(d)

    firmware._noisy_velocity = lying  # type: ignore[method-assign]


def glitch_position(server: SimServer, values: list[float], every_s: float = 1.0) -> list[float]:
    """Once E is in current mode, its POSITION reads `values[k]` (in turn) for one sample
    every `every_s` of arm time, the first half a period in: an encoder or frame glitch.
    Returns the list the arm times of the glitches are appended to."""
    firmware = server.firmware
    honest = firmware._noisy_position
    sent: list[float] = []
    due: list[float] = []

    def lying(d: Any) -> float:
        if d.spec.device_id == E and firmware.mode(int(E)) == Mode.CURRENT:
            now = firmware.time
            if not due:
                due.append(now + every_s / 2)
            elif now >= due[0]:
                due[0] += every_s
                sent.append(now)
                return values[(len(sent) - 1) % len(values)]
        return honest(d)

    firmware._noisy_position = lying  # type: ignore[method-assign]
    return sent


def silence_velocity(server: SimServer, after_s: float) -> None:
    """E stops sending VELOCITY `after_s` of arm time into current mode; its POSITION (and
    every other joint's) keeps coming."""
    firmware = server.firmware
    honest = firmware.report
    start: list[float] = []

    def silent(device_id: int, packet_id: int) -> Packet | None:
        if device_id == E and firmware.mode(int(E)) == Mode.CURRENT:
            if not start:
                start.append(firmware.time)
            if packet_id == PacketID.VELOCITY and firmware.time - start[0] > after_s:
                return None
        return honest(device_id, packet_id)

    firmware.report = silent  # type: ignore[method-assign]


def stick_velocity(server: SimServer, after_s: float) -> None:
    """`after_s` of arm time after E first goes into current mode (a controller has acted),
    E's VELOCITY sticks at the value it has then (`StuckReading`, the emulator's fault): the
    packets keep coming on time, only the value stops following the joint."""
    firmware = server.firmware
    honest = firmware.handle
    armed: list[float] = []

    def handle(packet: Packet) -> list[Packet]:
        replies = honest(packet)
        if not armed and firmware.mode(int(E)) == Mode.CURRENT:
            armed.append(firmware.time + after_s)
            firmware.inject_stuck(StuckReading(E, PacketID.VELOCITY, armed[0]))
        return replies

    firmware.handle = handle  # type: ignore[method-assign]


def _ddpg_run(server: SimServer, seconds: float) -> tuple[subprocess.Popen[str], dict[str, Any]]:
    """`reach-driver run --controller ddpg --json` to a target 0.3 rad (E) away."""
    q = server.snapshot().q
    target = [q[0] + 0.3, q[1] + 0.2, q[2] + 0.2, q[3] + 0.2]
    argv = ["--port", str(server.link), "--watchdog", "1", "run", "--controller", "ddpg"]
    proc = driver_process(*argv, "--target", *map(str, target), "--seconds", str(seconds), "--json")
    out, err = finish_process(proc)
    sys.stderr.write(err if "Traceback" in err else "")
    try:
        result = json.loads(out)
    except ValueError:
        result = {}
    result["_target_e"] = target[0]
    result["_traceback"] = "Traceback" in err
    return proc, result


def position_glitch(scale: float, tmp: str) -> Outcome:
    """E reports 1e6, 6.2 and -1 rad for one sample a second during a 6 s `ddpg` run: each
    is held, counted and reported; the real E stays at its target."""
    server = _server(tmp)
    sent = glitch_position(server, [1e6, 6.2, -1.0])
    try:
        proc, result = _ddpg_run(server, 6.0)
        true_e = float(server.snapshot().q[0])
        safe = _safe(server)
    finally:
        server.stop()
    off = abs(true_e - result["_target_e"])
    held = int(result.get("implausible_samples") or 0)
    events = [e for e in result.get("events", []) if e.startswith("implausible feedback")]
    return Outcome(
        "position-glitch",
        f"{len(sent)} one-sample glitches of E (1e6, 6.2, -1 rad)",
        f"exit {proc.returncode}, {held} samples held, {len(events)} events, the real E "
        f"{off * 1e3:.1f} mrad from its target at the end",
        proc.returncode == 0
        and safe
        and held >= 1
        and events != []
        and off < 0.05
        and not result["_traceback"],
    )


def stale_velocity(scale: float, tmp: str) -> Outcome:
    """E stops sending its velocity 0.5 s into an 11 s `ddpg` run (its position keeps
    coming): the run stops naming E's velocity, the arm made safe."""
    server = _server(tmp)
    silence_velocity(server, 0.5)
    try:
        proc, result = _ddpg_run(server, 11.0)
        safe = _safe(server)
    finally:
        server.stop()
    error = str(result.get("error"))
    return Outcome(
        "stale-velocity",
        "E's velocity silent from 0.5 s of an 11 s run",
        f"exit {proc.returncode} at {float(result.get('loop_seconds') or 0):.2f} s: "
        f"{error[:70]}...; left in {result.get('left_in')}",
        proc.returncode == 1
        and safe
        and "E (0x05) velocity" in error
        and "stale" in error
        and result.get("left_in") == "zero_velocity (confirmed by the arm)"
        and not result["_traceback"],
    )


def _hz(result: dict[str, Any]) -> str:
    measured = result.get("measured_hz")
    return f"{measured:.3g} Hz" if isinstance(measured, float) else "no rate measured"


def stuck_velocity(scale: float, tmp: str) -> Outcome:
    """E's velocity sticks at its value 0.2 s into a 6 s `ddpg` run, E still moving (the
    packets keep coming, so nothing is stale): the run stops naming E's stuck velocity, the
    arm made safe, and the stuck value is not taken for a wrong stream rate."""
    server = _server(tmp)
    stick_velocity(server, 0.2)
    try:
        proc, result = _ddpg_run(server, 6.0)
        safe = _safe(server)
    finally:
        server.stop()
    error = str(result.get("error"))
    said = error.split(" at t = ")[0] + ": " + error.partition("E: ")[2].split(", that")[0] + ")"
    return Outcome(
        "stuck-velocity",
        "E's velocity stuck from 0.2 s of a 6 s run",
        f"exit {proc.returncode} at {float(result.get('loop_seconds') or 0):.2f} s: "
        f"{said}; left in {result.get('left_in')}; stream measured at {_hz(result)}",
        proc.returncode == 1
        and safe
        and "implausible feedback from E (0x05)" in error
        and "velocity stuck at" in error
        and result.get("left_in") == "zero_velocity (confirmed by the arm)"
        and not result["_traceback"],
    )


def stream_at(server: SimServer, factor: float) -> None:
    """The arm streams at `factor` x the heartbeat frequency asked (a firmware that halves or
    doubles it)."""
    firmware = server.firmware
    honest = firmware._handlers[PacketID.HEARTBEAT_FREQUENCY]

    def wrong(targets: Any, packet: Packet) -> Any:
        hz = bytes((max(1, min(255, round(packet.data[0] * factor))),))
        return honest(targets, Packet(packet.device_id, packet.packet_id, hz))

    firmware._handlers[PacketID.HEARTBEAT_FREQUENCY] = wrong


def send_twice(server: SimServer) -> None:
    """Every packet the arm sends unprompted (the heartbeats) goes out twice."""
    firmware = server.firmware
    honest = firmware.steps
    firmware.steps = lambda n: [p for p in honest(n) for _ in (0, 1)]  # type: ignore[method-assign]


def stream_rate(scale: float, tmp: str) -> Outcome:
    """6 s `ddpg` runs against an arm that streams at half, then double, the rate asked (each
    must stop naming both rates, the arm made safe), then one that sends every packet twice
    (dropped and counted; the run completes)."""
    results: list[str] = []
    held = True
    for factor in (0.5, 2.0, None):
        server = _server(tmp)
        if factor is None:
            send_twice(server)
        else:
            stream_at(server, factor)
        try:
            proc, result = _ddpg_run(server, 6.0)
            safe = _safe(server)
        finally:
            server.stop()
        error = str(result.get("error"))
        measured = result.get("measured_hz")
        rate = f"{measured:.3g} Hz" if isinstance(measured, float) else "rate unmeasured"
        if factor is None:
            dups = int(result.get("duplicate_packets") or 0)
            results.append(f"twice: exit {proc.returncode}, {dups} duplicates dropped, {rate}")
            held &= proc.returncode == 0 and dups > 0 and safe
        else:
            stopped = float(result.get("loop_seconds") or 0)
            results.append(f"x{factor:g}: exit {proc.returncode} at {stopped:.2f} s, {error[:38]}")
            held &= (
                proc.returncode == 1
                and error.startswith("the arm streams at ")
                and "asked 20 Hz" in error
                and result.get("left_in") == "zero_velocity (confirmed by the arm)"
                and safe
            )
        held &= not result["_traceback"]
    return Outcome(
        "stream-rate",
        "3 runs: half rate, double rate, every packet twice",
        "; ".join(results),
        held,
    )


def nan_velocity(scale: float, tmp: str) -> Outcome:
    """The arm reports a NaN velocity for E mid-run (`ddpg`): one line naming it, the
    summary, how the arm was left, valid --json."""
    server = _server(tmp)
    lie_about_velocity(server, math.nan)
    try:
        q = server.snapshot().q
        target = [q[0] + 0.3, q[1] + 0.2, q[2] + 0.2, q[3] + 0.2]
        argv = ["--port", str(server.link), "--watchdog", "1", "run", "--controller", "ddpg"]
        proc = driver_process(*argv, "--target", *map(str, target), "--seconds", "5", "--json")
        out, err = finish_process(proc)
        safe = _safe(server)
    finally:
        server.stop()
    try:
        result = json.loads(out)
    except ValueError:
        result = {}
    error = str(result.get("error"))
    return Outcome(
        "nan-velocity",
        "1 NaN velocity mid-run",
        f"exit {proc.returncode}: {error[:60]}...; left in {result.get('left_in')}",
        proc.returncode == 1
        and safe
        and "non-finite velocity" in error
        and result.get("left_in") == "zero_velocity (confirmed by the arm)"
        and "Traceback" not in err,
    )


def bad_inputs(scale: float, tmp: str) -> Outcome:
    """Hostile command lines and files given to reach-driver and reach-sim: a period the
    watchdog cannot span, --record at the arm's own port and at a device, corrupt weights,
    deeply nested JSON, /dev/zero and a 1 GB file as --params. Each must end with one line
    and exit 2 before anything is sent (a pty stands for the arm and counts what reaches it)."""
    import contextlib
    import io
    import shutil

    from policy.controllers.weights import LEARNED_WEIGHTS
    from reach_driver.cli import main as driver_main

    master, slave = os.openpty()
    os.set_blocking(master, False)
    port = os.path.join(tmp, "alpha5-bad-inputs")
    os.symlink(os.ttyname(slave), port)
    nested = Path(tmp, "nested.json")
    nested.write_text("[" * 100_000 + "]" * 100_000)
    huge = Path(tmp, "huge.json")
    with open(huge, "wb") as f:
        f.truncate(2**30)
    weights = Path(tmp, "actor.npz")
    shutil.copy(LEARNED_WEIGHTS, weights)
    weights.with_suffix(".json").write_text("[]")
    run = ["--port", port, "run", "--controller", "pid", "--target", "3", "1.5", "1.5", "3"]
    run += ["--seconds", "1"]
    cases: list[tuple[str, Callable[[], int]]] = [
        ("--period 0.5", lambda: driver_main([*run, "--period", "0.5"])),
        ("--record PORT", lambda: driver_main([*run, "--record", os.ttyname(slave)])),
        ("--record /dev/null", lambda: driver_main([*run, "--record", os.devnull])),
        (
            "weights json a list",
            lambda: driver_main([*run[:4], "ddpg", *run[5:], "--param", f"weights={weights}"]),
        ),
        (
            "lambda params nested",
            lambda: driver_main([*run[:4], "lambda", *run[5:], "--param", f"params={nested}"]),
        ),
        ("reach-sim --params /dev/zero", lambda: _reach_sim(["--params", "/dev/zero"])),
        ("reach-sim --params 1 GB", lambda: _reach_sim(["--params", str(huge)])),
    ]
    before = _rss_mb()
    clean = 0
    try:
        for _name, case in cases:
            err = io.StringIO()
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                code = case()
            text = err.getvalue()
            clean += code == 2 and "Traceback" not in text
        try:
            leaked = len(os.read(master, 1 << 16))
        except BlockingIOError:
            leaked = 0
    finally:
        os.close(slave)
        os.close(master)
    grown = _rss_mb() - before
    child_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    return Outcome(
        "bad-inputs",
        f"{len(cases)} hostile options and files",
        f"{clean} refused with exit 2 and no traceback, {leaked} bytes reached the arm's port, "
        f"memory +{grown:.0f} MB (reach-sim at most {child_mb:.0f} MB)",
        clean == len(cases) and leaked == 0 and grown < 100.0 and child_mb < 500.0,
    )


def _reach_sim(argv: list[str]) -> int:
    """`reach-sim --no-pty ARGV` in a child (its stderr to ours), as an exit status; a child
    that runs a minute is killed and counts as not refusing."""
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "reach_sim_bridge.cli", "--no-pty", *argv]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        return -1
    sys.stderr.write(done.stderr)
    return done.returncode


def end_stop_hold(scale: float, tmp: str) -> Outcome:
    """600 mA into E's end stop, then the safe stop (ZERO_VELOCITY): the virtual arm's
    velocity loop must not keep the stall current (its integral starts at the applied
    current, and the joint cannot move to unwind it). Firmware and arm alone, in arm time."""
    fw = Firmware(Alpha5Arm())
    fw.handle(commands.current(E, 600.0))
    fw.tick(8.0)  # E from its start to the stop, then stalled there
    stalled = float(fw.arm.current_mA[0])
    fw.handle(commands.mode(E, Mode.ZERO_VELOCITY))
    fw.tick(2.0)
    after = float(fw.arm.current_mA[0])
    return Outcome(
        "end-stop-hold",
        "1 safe stop after a stall",
        f"E at q {fw.arm.q[0]:.3f} rad: {stalled:.0f} mA stalled, {after:.1f} mA 2 s (arm "
        "time) into zero velocity",
        abs(stalled) > 500.0 and abs(after) < 20.0,
    )


def encode_packet_as(device: int, packet_id: PacketID, *values: float) -> Packet:
    return Packet(device, packet_id, pack_floats(*values))


ATTACKS: dict[str, Callable[[float, str], Outcome]] = {
    "codec-fuzz": codec_fuzz,
    "junk-flood": junk_flood,
    "udp-stranger": udp_stranger,
    "request-flood": request_flood,
    "bad-commands": bad_commands,
    "watchdog": watchdog,
    "hostile-arm": hostile_arm,
    "exit-signals": exit_signals,
    "hang-at-interrupt": hang_at_interrupt,
    "move-timeout": move_timeout,
    "nan-velocity": nan_velocity,
    "position-glitch": position_glitch,
    "stale-velocity": stale_velocity,
    "stuck-velocity": stuck_velocity,
    "stream-rate": stream_rate,
    "bad-inputs": bad_inputs,
    "end-stop-hold": end_stop_hold,
    "udp-second-client": udp_second_client,
}
