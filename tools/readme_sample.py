#!/usr/bin/env python3
"""README.md's sample output, taken from a real run so that it cannot go stale.

README.md holds one ```text block between `<!-- sample:run -->` and `<!-- /sample -->`: a
`reach-driver` command as a user types it (`$ reach-driver --port /tmp/alpha5 run ...`) and
what it printed to a pipe. This tool serves the virtual arm that `reach-sim --link PATH`
serves (the nominal arm in its mid pose, real time), runs the block's command against it
through `reach-driver`'s own `main` (the port pointed at that arm), and then:

    tools/readme_sample.py           # says whether the block still matches (exit 1 if not)
    tools/readme_sample.py --write   # writes the fresh output into the block (make readme-sample)

Lines about the host rather than the run (the loop's timing, whether every state and current
arrived whole, how the run ended) are shown as `...`. A match means the same lines with the
same words, labels and columns, and every number within a tolerance of the one shown (REL,
LOOSER, ABS): the arm runs on the wall clock, so a loaded host shifts the figures a little.
tests/test_readme_sample.py runs the check.

Its logic lives here, not in a package: it serves this repository's README, not an install.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from protocol.extras import script_needs_extra

with script_needs_extra("tools/readme_sample.py", "sim"):
    from reach_sim_bridge.cli import build_parser as sim_parser
    from reach_sim_bridge.cli import config_from_args
    from reach_sim_bridge.emulator.server import SimServer

from reach_driver.cli import Exit
from reach_driver.cli import main as driver_main

README = Path(__file__).resolve().parents[1] / "README.md"
BEGIN = "<!-- sample:run -->"
END = "<!-- /sample -->"
PROMPT = "$ "
ELIDED = "..."
#: Lines that report the host the run went on, not the run: shown as ELIDED.
HOST_LINES = ("rate ", "loop period ", "saturated steps ", "torque = ")
#: A number matches the one shown when |ran - shown| <= ABS + rel * |shown|, rel REL or, on a
#: line whose label starts with a key of LOOSER, that. Measured at real time on a 2-core host
#: at load 8-15 (70 runs): the figures spread by 2.5 % at most, but a host pause early in the
#: move (about 1 run in 40) shifted the energy by up to 23 % and MIE and RMSE by up to 10 %.
#: ABS covers the last digit of 4-decimal angles and a count off by one.
REL = 0.2
LOOSER = {"energy": 0.4}
ABS = 0.002
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:e[-+]?\d+)?")


class SampleError(Exception):
    """The README has no sample block, or its command did not run to the end."""


@dataclass(frozen=True)
class Sample:
    command: str  # as the user types it, without the prompt
    lines: list[str]  # what it printed, host lines ELIDED


def read_sample(readme: str) -> Sample:
    """The command and output between the markers."""
    if readme.count(BEGIN) != 1 or readme.count(END) != 1:
        raise SampleError(f"README.md needs exactly one {BEGIN} ... {END} block")
    body = readme.split(BEGIN, 1)[1].split(END, 1)[0].strip().splitlines()
    if len(body) < 3 or body[0] != "```text" or body[-1] != "```":
        raise SampleError(f"the block between {BEGIN} and {END} must be one ```text fence")
    if not body[1].startswith(PROMPT):
        raise SampleError(f"the sample's first line must be the command, after {PROMPT!r}")
    return Sample(body[1][len(PROMPT) :], body[2:-1])


def block(sample: Sample) -> str:
    """The markers and the fence around the sample, as README.md holds them."""
    inner = "\n".join([PROMPT + sample.command, *sample.lines])
    return f"{BEGIN}\n```text\n{inner}\n```\n{END}"


def with_sample(readme: str, sample: Sample) -> str:
    """README.md with its block replaced by `sample`, everything else as it was."""
    read_sample(readme)  # the markers are there, once
    head, rest = readme.split(BEGIN, 1)
    tail = rest.split(END, 1)[1]
    return head + block(sample) + tail


def abridged(output: str) -> list[str]:
    """The printed lines with each run of host lines as one ELIDED."""
    lines: list[str] = []
    for line in output.rstrip("\n").splitlines():
        if line.startswith(HOST_LINES):
            if not lines or lines[-1] != ELIDED:
                lines.append(ELIDED)
        else:
            lines.append(line.rstrip())
    return lines


def run_sample(command: str, extra: Sequence[str] = ()) -> list[str]:
    """What `command` (a `reach-driver ... --port PORT ...` line) prints against the virtual
    arm `reach-sim --link` serves, abridged; `extra` options are added to it (tests give a
    loaded host a longer watchdog)."""
    words = shlex.split(command)
    if words[:1] != ["reach-driver"] or "--port" not in words[:-1]:
        raise SampleError(f"the sample must be a reach-driver command with --port: {command}")
    argv = words[1:]
    with tempfile.TemporaryDirectory(prefix="readme-sample-") as tmp:
        link = str(Path(tmp) / "arm")
        config = config_from_args(sim_parser().parse_args(["--link", link]))
        argv[argv.index("--port") + 1] = link
        out, err = io.StringIO(), io.StringIO()
        with SimServer(config) as arm:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                code = driver_main([*argv, *extra])
            failed = arm.error
    if code != Exit.OK or failed is not None:
        why = f"the virtual arm failed: {failed!r}" if failed else f"exit {int(code)}"
        raise SampleError(f"{command}: {why}\n{err.getvalue()}{out.getvalue()}")
    return abridged(out.getvalue())


def _shape(line: str) -> str:
    return " ".join(NUMBER.sub("#", line).split())


def differences(shown: Sequence[str], ran: Sequence[str]) -> list[str]:
    """Each way the lines a run printed differ from those shown: a line missing or added,
    other words, labels or columns, or a number further than the tolerance from the one
    shown. [] when the sample still holds."""
    out: list[str] = []
    for n, (a, b) in enumerate(zip(shown, ran, strict=False), 1):
        if _shape(a) != _shape(b):
            out.append(f"line {n}: shown {a.strip()!r}, now {b.strip()!r}")
            continue
        rel = next((r for label, r in LOOSER.items() if a.startswith(label)), REL)
        for x, y in zip(NUMBER.findall(a), NUMBER.findall(b), strict=True):
            if abs(float(y) - float(x)) > ABS + rel * abs(float(x)):
                out.append(f"line {n}: {x} shown, {y} now (tolerance {rel:.0%} + {ABS}): {a}")
    if len(shown) != len(ran):
        extra = ran[len(shown) :] or shown[len(ran) :]
        what = "printed now, not shown" if len(ran) > len(shown) else "shown, not printed now"
        out.append(f"{len(extra)} lines {what}, from: {extra[0].strip()!r}")
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="readme_sample.py",
        description=(
            "Run the command README.md's sample block shows against the virtual arm (real "
            "time) and check the block against its output, or write the output into it."
        ),
        epilog=f"The block: {BEGIN} ... {END} in README.md; its check: "
        "tests/test_readme_sample.py.",
    )
    p.add_argument("--write", action="store_true", help="write the fresh output into the block")
    p.add_argument("--readme", type=Path, default=README, help="default: the repository's")
    p.add_argument(
        "--watchdog",
        type=float,
        metavar="S",
        help="the driver's watchdog for the run, for a loaded host (it prints the same unless "
        "the watchdog trips)",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        text = args.readme.read_text(encoding="utf-8")
        sample = read_sample(text)
        extra = [] if args.watchdog is None else ["--watchdog", f"{args.watchdog:g}"]
        ran = run_sample(sample.command, extra)
    except (OSError, SampleError) as exc:
        print(f"readme_sample: {exc}", file=sys.stderr)
        return 2
    if args.write:
        args.readme.write_text(with_sample(text, Sample(sample.command, ran)), encoding="utf-8")
        print(f"wrote the sample in {args.readme}: {len(ran)} lines from `{sample.command}`")
        return 0
    found = differences(sample.lines, ran)
    for line in found:
        print(line)
    print("the sample holds" if not found else "stale: make readme-sample writes it afresh")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
