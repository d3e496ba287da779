"""Helpers shared by the test modules (import them as `from conftest import ...`) and the
virtual-arm fixtures, defined here once:

- `sim`: the virtual arm behind a pty linked at `tmp_path / "arm"`, at 4x real time unless
  told otherwise. A module (or class, or test) says how its arm differs with the `sim`
  marker, whose keywords are `SimConfig` fields: `pytestmark = pytest.mark.sim(speed=1.0,
  udp=LOOPBACK)`; one test may also pass them by indirect parametrisation
  (`@pytest.mark.parametrize("sim", [{"speed": 8.0}], indirect=True)`).
- `sim_port`: the address of that arm, once over the pty and once over UDP (the test runs
  twice; the module's marker must serve UDP).
- `sim_factory`: for a test that needs an arm set up otherwise or more than one: each arm it
  makes is stopped at the end of the test and its loop must not have failed.
- `arm_pauses_with_host`: the arms these fixtures make (and any other served in the test's
  process, e.g. by `run_episode_via_driver`) keep ARM time through a host pause, see there.

Every arm's loop must not have failed by the end of the test."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from policy.rl.config import DDPGConfig
    from policy.rl.trainer import Trainer
    from protocol.models import ArmModel
    from reach_sim_bridge.emulator.server import SimConfig, SimServer

#: What `sim_factory` hands a test: `make(**SimConfig fields) -> SimServer`.
SimFactory = Callable[..., "SimServer"]
#: Serve UDP on loopback, on a free port (`SimConfig(udp=LOOPBACK)`).
LOOPBACK = ("127.0.0.1", 0)
DEFAULT_SPEED = 4.0
#: Wall seconds a test's arm may fall behind its pace before it gives the time up instead of
#: catching up: 10 ms is 40 ms of arm time at 4x, under one 50 ms control period.
ARM_MAX_LAG_S = 0.01
#: The driver's watchdog (`--watchdog`, SafetyConfig.watchdog_s) for runs whose subject is not
#: the watchdog: its 0.2 s default is WALL time, and a loaded host deschedules a test process
#: past it now and then (0.204 and 0.212 s seen under a busy loop); 1 s is five times the
#: default. The watchdog's own tests keep 0.2 s.
WATCHDOG_S = 1.0
#: A control loop's wait for a complete state (ControlLoop's state_timeout_s, 0.5 s by default,
#: wall time) in runs that are not about lost feedback: 0.5 s host pauses happen under load.
FEEDBACK_TIMEOUT_S = 5.0


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "sim(**fields): SimConfig fields of the `sim` fixture's arm (conftest.py)"
    )


def sim_config(tmp_path: Path, **fields: Any) -> SimConfig:
    """The tests' virtual arm: 4x real time, a pty linked at `tmp_path / "arm"` (no link when
    the pty is off), with `fields` (SimConfig's) on top. (Imported here, not at the top: the
    codec's tests need no simulator.)"""
    from reach_sim_bridge.emulator.server import SimConfig

    defaults: dict[str, Any] = {"speed": DEFAULT_SPEED}
    if fields.get("pty", True):
        defaults["link"] = str(tmp_path / "arm")
    if fields.get("start") is not None:
        fields["start"] = tuple(float(v) for v in fields["start"])
    return SimConfig(**{**defaults, **fields})


@pytest.fixture
def arm_pauses_with_host(monkeypatch: pytest.MonkeyPatch) -> None:
    """A host pause stops the arm's clock too, for the in-process arms of the test.

    The simulator keeps real time: after a pause of its thread (a loaded 2-core host deschedules
    the test process for tens of ms now and then) it catches up, up to MAX_LAG_WALL_S (0.25 s,
    1 s of arm time at 4x) in one burst. A driver in the same process was paused too, so the
    arm moved that far on stale commands: latency in ARM time that an idle host never shows,
    which is what made the closed-loop tests' figures depend on the load. Here the arm gives up
    whatever it is behind past ARM_MAX_LAG_S (counted in its stats as lag_s), so arm and
    driver resume together and a run sees the same arm-time sequence whatever the load; the
    arm's speed is then at most, not exactly, its configured speed. (The server's loop reads
    MAX_LAG_WALL_S on every pass; a test process's arms share the patched value.)"""
    from reach_sim_bridge.emulator import server

    monkeypatch.setattr(server, "MAX_LAG_WALL_S", ARM_MAX_LAG_S)


@pytest.fixture
def sim_factory(tmp_path: Path, arm_pauses_with_host: None) -> Iterator[SimFactory]:
    """`make(**fields)`: a started arm (`sim_config`); `make(config=cfg)` one as given, and
    `make(..., start_now=False)` one not yet started (to set it up first). All are stopped at the
    end of the test, and none may have failed."""
    from reach_sim_bridge.emulator.server import SimServer

    made: list[SimServer] = []

    def make(
        *, config: SimConfig | None = None, start_now: bool = True, **fields: Any
    ) -> SimServer:
        if config is None:
            config = sim_config(tmp_path, **fields)
        elif fields:
            raise TypeError("give a SimConfig or its fields, not both")
        server = SimServer(config)
        made.append(server)
        if start_now:
            server.start()
        return server

    yield make
    for server in reversed(made):
        server.stop()
    assert [s.error for s in made if s.error is not None] == []


@pytest.fixture
def sim(request: pytest.FixtureRequest, sim_factory: SimFactory) -> SimServer:
    """The virtual arm as the closest `sim` marker and an indirect parameter say (module
    docstring); started, and stopped at the end of the test."""
    fields: dict[str, Any] = {}
    for marker in reversed(list(request.node.iter_markers("sim"))):  # module first, test last
        fields.update(marker.kwargs)
    fields.update(getattr(request, "param", None) or {})
    return sim_factory(**fields)


def udp_url(server: SimServer) -> str:
    """The `--port` a client gives to reach `server` over UDP."""
    assert server.udp_address is not None, "this arm serves no UDP (sim(udp=LOOPBACK))"
    host, port = server.udp_address
    return f"udp://{host}:{port}"


@pytest.fixture(params=["pty", "udp"])
def sim_port(request: pytest.FixtureRequest, sim: SimServer) -> str:
    """The `sim` arm's address, over its pty (the link) and over UDP: one run each."""
    if request.param == "udp":
        return udp_url(sim)
    assert sim.link is not None
    return str(sim.link)


def tiny(config: DDPGConfig, **overrides: object) -> DDPGConfig:
    """A training config that runs a few hundred steps in a couple of seconds."""
    import dataclasses

    base: dict[str, object] = dict(
        total_steps=400,
        learning_starts=100,
        eval_every=10**9,
        buffer_size=5_000,
        env=dataclasses.replace(config.env, episode_s=5.0),
    )
    base.update(overrides)
    return dataclasses.replace(config, **base)  # type: ignore[arg-type]


def train_quietly(config: DDPGConfig, run_dir: Path) -> Trainer:
    """`config` trained to its end in `run_dir` (train.csv there), the trainer closed after."""
    from policy.rl.trainer import Trainer

    trainer = Trainer(config, run_dir, log=lambda _: None)
    try:
        trainer.run(csv_path=run_dir / "train.csv")
    finally:
        trainer.close()
    return trainer


def run_tool(script: str, *argv: str) -> subprocess.CompletedProcess[str]:
    """tools/`script` run as a user runs it, from the repository's root; its output kept."""
    root = Path(__file__).resolve().parents[1]
    return subprocess.run(
        [sys.executable, str(root / "tools" / script), *argv],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=root,
    )


def still_actor(path: Path, model: ArmModel) -> Path:
    """A weights file at `path` holding an actor for `model`'s arm that asks for no current
    (its output layer zeroed): the plumbing of an arm's actor, not a policy."""
    import torch

    from policy.rl.checkpoint import save_actor_npz
    from policy.rl.config import DDPGConfig
    from policy.rl.networks import Actor

    config = DDPGConfig.scratch(hidden=(16, 16)).on(model)
    actor = Actor(config.env.observation.size_for(model.n_joints), model.n_joints, config.hidden)
    with torch.no_grad():
        for tensor in actor.linears()[-1].parameters():
            tensor.zero_()
    save_actor_npz(path, actor, config)
    return path


def wait_until(
    predicate: Callable[[], object], timeout: float = 20.0, poll_s: float = 0.005
) -> bool:
    """Poll `predicate` until it is truthy or `timeout` seconds pass; its last verdict. The
    default is a deadline, not a measure: what a test waits for happens in well under a
    second on an idle host, and a loaded one (2 cores, several runs) may take many times that;
    a passing test never waits it out."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(poll_s)
    return bool(predicate())


def recorded_steps(path: Path) -> list[int]:
    """The steps a .rrd file holds so far ([] while it does not read yet: a file another process
    is still writing may not), for waiting on a recording instead of sleeping."""
    from reach_driver.rrd_summary import read_recording

    try:
        return [int(k) for k in read_recording(path).step]
    except Exception:
        return []


def default_sigint() -> None:
    """`preexec_fn` for a child that a test interrupts with SIGINT: Ctrl-C's default action,
    as a shell in the foreground gives it. A non-interactive shell's background jobs (CI run
    with `&`) start with SIGINT ignored, and Python then never raises KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
