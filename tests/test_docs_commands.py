"""Every command in the ```sh blocks of README.md, docs/hil.md and docs/usage.md still works.

`reach-driver` commands run against a virtual arm (its pty or UDP address put where the text
names a port; a virtual Bravo 7 where the port names a `bravo7`; durations cut short, run in
one directory; a recording that `inspect` or `export` reads is made first by the documented
command that records it, where no earlier command on this worker has);
a command with `...` in it, `reach-sim` (a server), `rerun` (a viewer) and the tools (minutes of
work) are parsed by their own parser or asked for `--help`; `make` targets must exist. A command
that no longer parses fails.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from reach_driver.cli import Exit, main
from reach_driver.cli.parser import build_parser
from reach_sim_bridge.emulator.server import SimConfig, SimServer

ROOT = Path(__file__).resolve().parents[1]
DOCS = ("README.md", "docs/hil.md", "docs/usage.md")
SHORT_SECONDS = "1"
MONITOR_SECONDS = "0.5"


def sh_commands(path: Path) -> list[str]:
    """The commands of the file's ```sh blocks: comments dropped, continuations joined."""
    commands: list[str] = []
    for block in re.findall(r"^```sh\n(.*?)^```", path.read_text(), re.DOTALL | re.MULTILINE):
        pending = ""
        for raw in block.splitlines():
            line = raw.split(" #", 1)[0].rstrip() if not raw.lstrip().startswith("#") else ""
            if line.endswith("\\"):
                pending += line[:-1] + " "
                continue
            line = (pending + line).strip()
            pending = ""
            if line:
                commands.append(line)
    return commands


ALL = [(doc, cmd) for doc in DOCS for cmd in sh_commands(ROOT / doc)]


def test_the_docs_have_commands_to_check() -> None:
    assert len([c for d, c in ALL if d == "README.md"]) >= 8
    assert len([c for d, c in ALL if d == "docs/hil.md"]) >= 6
    assert len([c for d, c in ALL if d == "docs/usage.md"]) >= 15


def _program(word: str) -> str:
    return Path(word).name  # .venv/bin/reach-driver -> reach-driver


def _tool_parser(script: str) -> argparse.ArgumentParser | None:
    """The parser of a tool whose command line lives in a package (the module the script takes
    `main` from, which also holds `build_parser`); None for a tool that parses for itself."""
    tree = ast.parse((ROOT / script).read_text(encoding="utf-8"))
    inner = [n for stmt in tree.body if isinstance(stmt, ast.With) for n in stmt.body]
    for node in [*tree.body, *inner]:  # imports inside `with script_needs_extra(...)` too
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if any(alias.name == "main" for alias in node.names):
                build = getattr(importlib.import_module(node.module), "build_parser", None)
                return build() if build is not None else None
    return None


def _parses(parser: argparse.ArgumentParser, argv: list[str]) -> None:
    try:
        parser.parse_args(argv)
    except SystemExit as exc:  # argparse's way of saying no
        pytest.fail(f"{parser.prog} {' '.join(argv)}: does not parse (exit {exc.code})")


def _help(cmd: list[str]) -> None:
    done = subprocess.run(
        [*cmd, "--help"], cwd=ROOT, capture_output=True, text=True, timeout=300, check=False
    )
    assert done.returncode == 0, done.stderr
    assert "usage" in done.stdout.lower(), done.stdout


@pytest.fixture(scope="module")
def arm(tmp_path_factory):
    """A virtual arm sped up 8x, and a directory the commands run in."""
    work = tmp_path_factory.mktemp("docs")
    server = SimServer(SimConfig(speed=8.0, link=str(work / "arm"), udp=("127.0.0.1", 0)))
    server.start()
    yield server, work
    server.stop()
    assert server.error is None


@pytest.fixture(scope="module")
def bravo(arm):
    """A virtual Bravo 7 beside `arm`, for the commands whose port names a `bravo7`."""
    from protocol.models import BRAVO7

    _, work = arm
    server = SimServer(SimConfig(speed=8.0, link=str(work / "bravo7"), model=BRAVO7))
    server.start()
    yield server
    server.stop()
    assert server.error is None


def _for_the_virtual_arm(argv: list[str], server: SimServer) -> list[str]:
    """The port pointed at the virtual arm, long runs cut short, monitor bounded."""
    out = list(argv)
    if "--port" in out:
        i = out.index("--port") + 1
        if out[i].startswith("udp://"):
            assert server.udp_address is not None
            host, port = server.udp_address
            out[i] = f"udp://{host}:{port}"
        else:
            out[i] = str(server.link)
    if "--seconds" in out:
        out[out.index("--seconds") + 1] = SHORT_SECONDS
    if "monitor" in out and "--seconds" not in out:
        out += ["--seconds", MONITOR_SECONDS]
    return out


@pytest.mark.parametrize(("doc", "command"), ALL, ids=[f"{d}: {c}" for d, c in ALL])
def test_documented_command_works(doc, command, arm, request, monkeypatch, capsys) -> None:
    server, work = arm
    words = shlex.split(command)
    program = _program(words[0])
    if program == "python":
        program, words = _program(words[1]), words[1:]
    args = words[1:]
    monkeypatch.chdir(work)
    if program == "make":
        makefile = (ROOT / "Makefile").read_text()
        for target in args:
            assert re.search(rf"^{re.escape(target)}:", makefile, re.MULTILINE), target
    elif program == "reach-driver":
        if "..." in args:  # an elided command: the command before it must parse
            head = args[: args.index("...")]
            _parses(build_parser(), head + _required(head))
            return
        for needed in _recordings_read(args):
            if not (work / needed).exists():  # its maker ran on another worker (xdist)
                _run_driver(_recorded_by(needed), server, request, capsys)
        _run_driver(args, server, request, capsys)
    elif program == "reach-sim":
        from reach_sim_bridge.cli import build_parser as sim_parser

        _parses(sim_parser(), args)  # a server: parsed, not started (the fixture is one)
        _help([sys.executable, "-m", "reach_sim_bridge"])
    elif program == "pip":
        _installs_what_pyproject_defines(args)
    elif program == "rerun":
        _help([str(Path(sys.executable).with_name("rerun"))])  # a viewer needs a display
    elif program.startswith("tools/") or program.endswith(".py"):
        script = words[0] if words[0].startswith("tools/") else program
        parser = _tool_parser(script)
        if parser is not None and args != ["--help"]:
            _parses(parser, args)
        _help([sys.executable, str(ROOT / script)])
    else:
        pytest.fail(f"{doc}: no rule for {command!r}; add one to this test")


def _run_driver(args: list[str], server: SimServer, request, capsys) -> None:
    """`reach-driver ARGS` against the virtual arm (the Bravo 7 where the port names one)."""
    port = args[args.index("--port") + 1] if "--port" in args else ""
    if "bravo7" in port:
        server = request.getfixturevalue("bravo")
    argv = _for_the_virtual_arm(args, server)
    _parses(build_parser(), argv)
    code = main(argv)
    captured = capsys.readouterr()
    assert code == Exit.OK, f"{' '.join(argv)} -> {code}\n{captured.out}\n{captured.err}"


def _recordings_read(args: list[str]) -> list[str]:
    """The recordings `reach-driver inspect|export FILE.rrd` reads."""
    if not {"inspect", "export"} & set(args):
        return []
    return [a for a in args if a.endswith(".rrd")]


def _recorded_by(name: str) -> list[str]:
    """The arguments of the documented command that records `name` (`run ... --record NAME`)
    against the virtual arm: the order the docs give it in is not the order xdist's workers
    run their share in."""
    for _, command in ALL:
        words = shlex.split(command)
        if _program(words[0]) == "reach-driver" and "--record" in words:
            if words[words.index("--record") + 1] == name:
                return words[1:]
    pytest.fail(f"no documented command records {name}")


def _installs_what_pyproject_defines(args: list[str]) -> None:
    """`pip install reach-stack[EXTRA,...]` (or `.[...]`): each extra is one pyproject.toml
    defines (read as text: tomllib is Python 3.11+)."""
    assert args[:1] == ["install"], args
    text = (ROOT / "pyproject.toml").read_text()
    section = text.split("[project.optional-dependencies]", 1)[1].split("\n[", 1)[0]
    defined = set(re.findall(r"^([\w-]+) = ", section, re.MULTILINE))
    for arg in args[1:]:
        if arg.startswith("-"):
            continue
        name, _, rest = arg.partition("[")
        assert name in ("reach-stack", "."), arg
        extras = {e.strip() for e in rest.rstrip("]").split(",") if e.strip()}
        assert extras <= defined, f"{arg}: pyproject.toml defines {sorted(defined)}"


def _required(head: list[str]) -> list[str]:
    """What an elided `run ...` needs to parse (the text elides exactly these)."""
    if head and head[-1] == "run":
        return ["--controller", "pid", "--target", "3", "1.5", "1.5", "3", "--seconds", "1"]
    return []
