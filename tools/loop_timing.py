#!/usr/bin/env python3
"""Does the control loop keep time on a busy machine? The README's `run` command, N times,
beside a chosen load, with the watchdog trips and the loop period's percentiles.

    .venv/bin/python tools/loop_timing.py --runs 10 --seconds 20 --load cpu:2 sim threads:4 --tty
    .venv/bin/python tools/loop_timing.py --runs 50 --seconds 6 --load sim gil:8 mem --viewer serve

Each run is the README's command (`reach-driver --port ARM run --controller ddpg --target 3.5
1.2 1.8 1.0 --seconds S --record runK.rrd`, this tree's code: `python -m reach_driver`)
against one `reach-sim --link ARM --udp ... --record sim.rrd` started first, as the README
starts it. The loop period is the wall time from one command to the next (what the watchdog
judges), read back from each run's recording (`link/loop_period`) and pooled over the runs;
the recordings' summaries also take the longest gaps apart (`reach_driver.loop_timing`).

Loads (each a process of its own beside the runs, at the driver's priority unless --nice):

  cpu[:N]      N busy loops (a plain CPU hog)
  sim[:N]      N more reach-sims, each recording its own .rrd
  threads[:N]  one process whose N threads multiply matrices (numpy releases the GIL)
  gil[:N]      one process whose N Python threads contend for its GIL
  mem[:N]      N processes each allocating, touching and freeing 256 MB over and over
  render[:N]   one process redrawing a rich live table at 30 Hz to a pty nobody reads fast

`--tty` runs each command on a pseudo-terminal (120x40), so `run` draws its live table as it
does for a person; `--viewer serve` adds the live viewer's gRPC server and web server.
`--realtime MODE` passes `run --realtime MODE` (default: the driver's own, try: real-time
priority for the loop and the link's reader where permitted; `--realtime try off` takes
turns, an A/B under the same load); `--sim-prefix 'chrt -f 10'`
starts the arm's reach-sim real-time too, as a real arm keeps time on its own processor
whatever the host does.

Exit status: 0 when no run tripped its watchdog or failed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import pty
import re
import shlex
import signal
import struct
import subprocess
import sys
import tempfile
import termios
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from reach_driver.rrd_summary import RecordingReadError, read_recording  # noqa: E402

#: The README's run command, after `--port ARM`.
README_RUN = ["run", "--controller", "ddpg", "--target", "3.5", "1.2", "1.8", "1.0"]
LOADS = ("cpu", "sim", "threads", "gil", "mem", "render")
ANSI = re.compile(r"\x1b\[[0-9;?]*[a-zA-Z]|\r")

_HOG = r"""
import sys, threading, time
kind, n = sys.argv[1], int(sys.argv[2])
if kind == "cpu":
    while True:
        pass
elif kind == "threads":
    import numpy as np
    def work():
        x = np.random.default_rng().random((300, 300))
        while True:
            x = (x @ x) / 300.0
    for _ in range(n):
        threading.Thread(target=work, daemon=True).start()
elif kind == "gil":
    def spin():
        while True:
            sum(range(1000))
    for _ in range(n):
        threading.Thread(target=spin, daemon=True).start()
elif kind == "mem":
    import numpy as np
    while True:
        a = np.ones(256 * 1024 * 1024 // 8)
        a += 1.0
        del a
elif kind == "render":
    from rich.console import Console
    from rich.live import Live
    from rich.table import Table
    def table():
        t = Table(title=f"{time.monotonic():.3f}")
        for c in range(8):
            t.add_column(f"column {c}")
        for r in range(20):
            t.add_row(*(f"{time.monotonic() * (r + c):.4f}" for c in range(8)))
        return t
    with Live(get_renderable=table, refresh_per_second=30, console=Console(force_terminal=True)):
        while True:
            time.sleep(1)
while True:
    time.sleep(1)
"""


def _parse_load(spec: str) -> tuple[str, int]:
    kind, _, count = spec.partition(":")
    if kind not in LOADS:
        raise argparse.ArgumentTypeError(f"unknown load {kind!r}; one of {', '.join(LOADS)}")
    try:
        n = int(count) if count else 1
    except ValueError:
        raise argparse.ArgumentTypeError(f"{spec!r}: the count after ':' is a number") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"{spec!r}: the count is at least 1")
    return kind, n


def _python(*args: str) -> list[str]:
    return [sys.executable, *args]


def _env(tree: Path = ROOT) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(tree), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


class Sim:
    """`reach-sim --link LINK --record sim.rrd [--udp ...]`, waited for until its link exists."""

    def __init__(
        self, where: Path, name: str, udp: str | None, nice: int, prefix: list[str] | None = None
    ) -> None:
        self.link = where / name
        cmd = [*(prefix or []), *_python("-m", "reach_sim_bridge", "--link", str(self.link))]
        if udp:
            cmd += ["--udp", udp]
        cmd += ["--record", str(where / f"{name}.rrd")]
        self.proc = subprocess.Popen(
            cmd,
            cwd=where,
            env=_env(),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=(lambda: os.nice(nice)) if nice else None,
            start_new_session=True,  # started from a terminal of its own, as the README does
        )
        deadline = time.monotonic() + 60
        while not self.link.exists():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"reach-sim {name} did not start")
            time.sleep(0.05)

    def stop(self) -> None:
        _stop(self.proc)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


class Load:
    """The load processes beside the runs."""

    def __init__(self, specs: list[tuple[str, int]], where: Path, nice: int) -> None:
        self.procs: list[subprocess.Popen[bytes]] = []
        self.sims: list[Sim] = []
        self._ptys: list[int] = []
        pre = (lambda: os.nice(nice)) if nice else None
        for kind, n in specs:
            if kind == "sim":
                for k in range(n):
                    self.sims.append(Sim(where, f"load-sim{len(self.sims)}-{k}", None, nice))
                continue
            copies = n if kind in ("cpu", "mem") else 1
            for _ in range(copies):
                out: int = subprocess.DEVNULL
                if kind == "render":  # a terminal drained slowly, as a busy one is
                    master, slave = pty.openpty()
                    _winsize(slave, 40, 160)
                    self._ptys.append(master)
                    threading.Thread(target=_drain, args=(master, 0.05), daemon=True).start()
                    out = slave
                self.procs.append(
                    subprocess.Popen(
                        _python("-c", _HOG, kind, str(n)),
                        stdout=out,
                        stderr=out,
                        stdin=subprocess.DEVNULL,
                        preexec_fn=pre,
                        env=_env(),
                        start_new_session=True,  # another program, not part of the run
                    )
                )
                if out is not subprocess.DEVNULL:
                    os.close(out)

    def stop(self) -> None:
        for p in self.procs:
            _stop(p)
        for s in self.sims:
            s.stop()


def _winsize(fd: int, rows: int, cols: int) -> None:
    fcntl.ioctl(fd, termios.TIOCSWINSZ, struct.pack("HHHH", rows, cols, 0, 0))


def _drain(master: int, pause_s: float, sink: list[bytes] | None = None) -> None:
    """Read a pty until it closes, as a terminal does (`pause_s` between reads: a slow one)."""
    while True:
        try:
            data = os.read(master, 65536)
        except OSError:
            return
        if not data:
            return
        if sink is not None:
            sink.append(data)
        if pause_s:
            time.sleep(pause_s)


def _watch(pid: int, out: Path) -> threading.Thread:
    """Every ~2 ms until `pid` exits, each of its threads' state, CPU and run-queue time
    (/proc/PID/task/*/schedstat) and kernel wait channel, into `out` (JSON rows of
    [seconds, {tid: [name, state, cpu_ns, runqueue_ns, wchan]}]): which thread held the
    process up during a long gap."""

    def sample() -> None:
        rows: list[tuple[float, dict[str, tuple[str, str, int, int, str]]]] = []
        t0 = time.monotonic()
        while True:
            try:
                tids = os.listdir(f"/proc/{pid}/task")
            except OSError:
                break
            snap = {}
            for tid in tids:
                base = f"/proc/{pid}/task/{tid}"
                try:
                    stat = Path(f"{base}/stat").read_text()
                    cpu, queue = Path(f"{base}/schedstat").read_text().split()[:2]
                    wchan = Path(f"{base}/wchan").read_text()
                except OSError:
                    continue
                name = stat[stat.index("(") + 1 : stat.rindex(")")]
                snap[tid] = (name, stat[stat.rindex(")") + 2], int(cpu), int(queue), wchan)
            if not snap:
                break
            rows.append((time.monotonic() - t0, snap))
            time.sleep(0.002)
        out.write_text(json.dumps(rows))

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    return thread


@dataclass
class RunResult:
    index: int
    exit_code: int
    wall_s: float
    watchdog: str | None  # the trip's reason, from the command's output
    failure: str | None  # the "run failed: ..." line, if any
    periods_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    summary: dict[str, object] = field(default_factory=dict)
    tree: Path = ROOT
    prefixed: bool = False
    load: float = float("nan")  # the 1-minute load average as the run ended
    realtime: str | None = None  # the `run --realtime` mode given (None: the default)


WATCHDOG_LINE = re.compile(r"watchdog: (.*?)(?:; put |\n|$)")
FAILED_LINE = re.compile(r"run failed: (.*)")


def run_once(
    index: int,
    port: Path,
    where: Path,
    seconds: float,
    viewer: list[str],
    tty: bool,
    spy: str | None = None,
    sample: bool = False,
    tree: Path = ROOT,
    prefix: list[str] | None = None,
    realtime: str | None = None,
) -> RunResult:
    rec = where / f"run{index}.rrd"
    wrap = []
    if spy:  # py-spy's samples of every thread, idle ones too, in order (speedscope)
        out = str(where / f"run{index}.speedscope.json")
        wrap = [spy, "record", "--idle", "--threads", "--rate", "250", "--format", "speedscope"]
        wrap += ["--nonblocking", "-o", out, "--"]
    if prefix:
        wrap = [*prefix, *wrap]
    cmd = wrap + _python(
        "-m", "reach_driver", "--port", str(port), *README_RUN, "--seconds", f"{seconds:g}"
    )
    cmd += ["--record", str(rec), *viewer]
    if realtime:
        cmd += ["--realtime", realtime]
    started = time.monotonic()
    chunks: list[bytes] = []
    if tty:
        master, slave = pty.openpty()
        _winsize(slave, 40, 120)
        reader = threading.Thread(target=_drain, args=(master, 0.0, chunks), daemon=True)
        reader.start()
        proc = subprocess.Popen(
            cmd,
            stdin=slave,
            stdout=slave,
            stderr=slave,
            env=_env(tree),
            cwd=where,
            close_fds=True,
            start_new_session=True,  # a terminal's session, as a person's shell gives it
        )
        os.close(slave)
        watcher = _watch(proc.pid, where / f"run{index}.threads.json") if sample else None
        code = proc.wait()
        if watcher is not None:
            watcher.join(10)
        reader.join(10)
        os.close(master)
    else:
        proc = subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env=_env(tree),
            cwd=where,
            start_new_session=True,
        )
        watcher = _watch(proc.pid, where / f"run{index}.threads.json") if sample else None
        captured, _ = proc.communicate()
        code = proc.returncode
        chunks = [captured]
        if watcher is not None:
            watcher.join(10)
    wall = time.monotonic() - started
    text = ANSI.sub("", b"".join(chunks).decode(errors="replace"))
    flat = " ".join(text.split())
    trip = WATCHDOG_LINE.search(flat)
    failed = FAILED_LINE.search(flat)
    result = RunResult(
        index, code, wall, trip.group(1) if trip else None, failed.group(1) if failed else None
    )
    (where / f"run{index}.log").write_text(text)
    try:
        recorded = read_recording(rec)
        if recorded.loop_period_ms is not None:
            periods = recorded.loop_period_ms
            result.periods_ms = periods[np.isfinite(periods)]
        result.summary = recorded.summary
    except (RecordingReadError, OSError) as exc:
        result.failure = result.failure or f"recording unreadable: {exc}"
    return result


def percentiles(periods_ms: np.ndarray) -> dict[str, float]:
    if periods_ms.size == 0:
        return {k: float("nan") for k in ("p50", "p99", "p99.9", "max")}
    p50, p99, p999 = np.percentile(periods_ms, [50, 99, 99.9])
    return {"p50": p50, "p99": p99, "p99.9": p999, "max": float(periods_ms.max())}


def fmt(p: dict[str, float]) -> str:
    return " / ".join(f"{k} {v:.1f}" for k, v in p.items()) + " ms"


def realtime_granted(r: RunResult) -> bool | None:
    """Whether the run's loop and reader had real-time priority (its recording's summary;
    None when it does not say)."""
    got = r.summary.get("realtime")
    return bool(got.get("granted")) if isinstance(got, dict) else None


def longest_gaps(r: RunResult) -> list[dict[str, Any]]:
    """The run's longest gaps between commands, taken apart, as its recording's summary
    holds them (`reach_driver.loop_timing.Gap.as_dict`), longest first."""
    gaps = r.summary.get("longest_gaps")
    return [g for g in gaps if isinstance(g, dict)] if isinstance(gaps, list) else []


def summarize(label: str, results: list[RunResult]) -> dict[str, object]:
    """Print and return the figures of a set of runs: trips, failures, the pooled loop
    period, and the largest part of each gap over 100 ms."""
    pooled = np.concatenate([r.periods_ms for r in results]) if results else np.zeros(0)
    trips = sum(1 for r in results if r.watchdog)
    failed = sum(1 for r in results if r.exit_code != 0)
    granted = sum(1 for r in results if realtime_granted(r))
    loads = [r.load for r in results if np.isfinite(r.load)]
    load = f"{min(loads):.1f}-{max(loads):.1f}" if loads else "unknown"
    causes: dict[str, int] = {}
    for r in results:
        for g in longest_gaps(r):
            if float(g.get("gap_s", 0)) > 0.1:
                causes[str(g["cause"])] = causes.get(str(g["cause"]), 0) + 1
    print(
        f"\n{label + ': ' if label else ''}{trips} watchdog trip(s), {failed} run(s) not exit 0, "
        f"of {len(results)}; loop period over {pooled.size} gaps: {fmt(percentiles(pooled))}; "
        f"real-time priority in {granted}; load average {load}"
    )
    if causes:
        print(
            "gaps over 100 ms, by their largest part: "
            + "; ".join(f"{name} {n}" for name, n in sorted(causes.items(), key=lambda kv: -kv[1]))
        )
    return {
        "runs": len(results),
        "watchdog_trips": trips,
        "not_ok": failed,
        "realtime_granted": granted,
        "load_average": load,
        "loop_period_ms": percentiles(pooled),
        "gap_causes": causes,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--runs", type=int, default=10, help="runs of the command (default 10)")
    parser.add_argument("--seconds", type=float, default=20.0, help="each run's --seconds (20)")
    parser.add_argument("--load", nargs="*", type=_parse_load, default=[], metavar="KIND[:N]")
    parser.add_argument("--nice", type=int, default=0, help="niceness of the load (default 0)")
    parser.add_argument("--tty", action="store_true", help="run on a pty: the live table draws")
    parser.add_argument(
        "--viewer", nargs="+", metavar="WORD", help="pass --viewer to run, e.g. --viewer serve"
    )
    parser.add_argument("--out", type=Path, help="keep the runs' files here (default: a temp dir)")
    parser.add_argument("--json", type=Path, help="write the figures here")
    parser.add_argument("--py-spy", metavar="EXE", help="sample each run with this py-spy")
    parser.add_argument(
        "--prefix",
        type=shlex.split,
        metavar="COMMAND",
        help="run each command under this (e.g. --prefix 'chrt -f 10', or 'nice -n 5')",
    )
    parser.add_argument(
        "--sim-prefix",
        type=shlex.split,
        metavar="COMMAND",
        help="run the arm's reach-sim under this (e.g. 'chrt -f 20': a virtual arm that keeps "
        "time, as a real one does)",
    )
    parser.add_argument(
        "--realtime",
        nargs="+",
        choices=("try", "require", "off"),
        metavar="MODE",
        help="pass `run --realtime` this (try, require, off; default: not given, the driver's "
        "own, try); several modes take turns run by run (an A/B under the same load: "
        "--realtime try off), each summarised apart",
    )
    parser.add_argument(
        "--prefix-alternate",
        action="store_true",
        help="only every second run under --prefix (an A/B: A without, B with)",
    )
    parser.add_argument(
        "--against",
        type=Path,
        metavar="TREE",
        help="alternate the runs with this checkout's driver (an A/B under the same load)",
    )
    parser.add_argument(
        "--threads-trace",
        action="store_true",
        help="trace each run's threads (state, CPU, run queue; runK.threads.json in --out)",
    )
    args = parser.parse_args(argv)

    tmp = None if args.out else tempfile.TemporaryDirectory(prefix="loop-timing-")
    where = args.out or Path(tmp.name)  # type: ignore[union-attr]
    where.mkdir(parents=True, exist_ok=True)
    viewer = ["--viewer", *args.viewer] if args.viewer else []
    what = " ".join(f"{k}:{n}" for k, n in args.load) or "none"
    print(
        f"{args.runs} x README run (ddpg, --record{' ' + ' '.join(viewer) if viewer else ''}, "
        f"{args.seconds:g} s{', on a pty' if args.tty else ''}); load: {what}; "
        f"{os.cpu_count()} CPUs"
    )
    sim = Sim(where, "alpha5", "127.0.0.1:0", 0, args.sim_prefix)
    load = Load(args.load, where, args.nice)
    results: list[RunResult] = []
    modes: list[str | None] = args.realtime or [None]
    try:
        time.sleep(1.0)  # let the load start up
        for k in range(1, args.runs + 1):
            mode = modes[(k - 1) % len(modes)]
            tree = args.against if args.against is not None and k % 2 == 0 else ROOT
            prefix = args.prefix if not args.prefix_alternate or k % 2 == 0 else None
            r = run_once(
                k,
                sim.link,
                where,
                args.seconds,
                viewer,
                args.tty,
                args.py_spy,
                args.threads_trace,
                tree,
                prefix,
                mode,
            )
            r.realtime = mode
            r.prefixed = bool(prefix)
            r.tree = tree
            r.load = os.getloadavg()[0]
            results.append(r)
            p = percentiles(r.periods_ms)
            longest = longest_gaps(r)
            cause = ""
            if longest:
                g = longest[0]
                cause = f"; longest {1e3 * float(g['gap_s']):.0f} ms: {g['cause']}"
            said = f" WATCHDOG: {r.watchdog}" if r.watchdog else ""
            note = f" FAILED: {r.failure}" if r.failure and not r.watchdog else ""
            ab = args.against is not None or args.prefix_alternate
            which = ("B" if tree != ROOT or r.prefixed else "A") if ab else ""
            which += f" {mode}" if len(modes) > 1 else ""
            rt = {True: " rt", False: " no-rt", None: ""}[realtime_granted(r)]
            print(
                f"run {k:3d}{which} exit {r.exit_code} load {r.load:.1f}{rt} | "
                f"{fmt(p)}{cause}{said}{note}",
                flush=True,
            )
    except KeyboardInterrupt:  # Ctrl-C: the runs done so far are summarised
        print(f"\ninterrupted: {len(results)} of {args.runs} runs done")
    finally:
        load.stop()
        sim.stop()
    groups = {"": results}
    if len(modes) > 1:
        groups = {f"--realtime {m}": [r for r in results if r.realtime == m] for m in modes}
    if args.against is not None:
        groups = {
            f"A ({ROOT})": [r for r in results if r.tree == ROOT],
            f"B ({args.against})": [r for r in results if r.tree != ROOT],
        }
    if args.prefix_alternate:
        groups = {
            "A (as is)": [r for r in results if not r.prefixed],
            f"B ({' '.join(args.prefix or [])})": [r for r in results if r.prefixed],
        }
    figures = {label: summarize(label, rs) for label, rs in groups.items()}
    failed = [r for r in results if r.exit_code != 0]
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "runs": len(results),
                    "seconds": args.seconds,
                    "load": what,
                    "tty": args.tty,
                    "viewer": viewer,
                    "groups": figures,
                    "per_run": [
                        {
                            "tree": str(r.tree),
                            "exit": r.exit_code,
                            "watchdog": r.watchdog,
                            "failure": r.failure,
                            "loop_period_ms": percentiles(r.periods_ms),
                            "load_average": r.load,
                            "realtime_mode": r.realtime,
                            "realtime": r.summary.get("realtime"),
                            "longest_gaps": r.summary.get("longest_gaps"),
                        }
                        for r in results
                    ],
                },
                indent=1,
            )
        )
    if tmp is not None:
        tmp.cleanup()
    return 0 if not failed else 1


if __name__ == "__main__":
    sys.exit(main())
