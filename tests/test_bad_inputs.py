"""Bad input from a person's command line or files: a period the watchdog cannot span, a
recording pointed at the arm's own port, corrupt weights, crafted recordings, hostile JSON and
files that never end. Each gets one clear line and a documented exit status, no traceback,
before anything reaches the arm. Each test here failed on the code before its fix."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from policy.controllers.weights import ActorWeights
from protocol import DeviceID, commands
from reach_driver import ArmClient, SafetyConfig, open_transport
from reach_driver.cli import Exit, main
from reach_driver.cli.exits import for_operator
from reach_driver.control import ControlLoop
from reach_driver.watchdog import Watchdog

E = int(DeviceID.E)
TARGET = ["3.0", "1.5", "1.5", "3.0"]
NO_ARM = "/nonexistent/reach-test-port"  # connecting to it would exit 4 (no arm)


def _one_clear_line(err: str) -> None:
    assert "Traceback" not in err, err
    assert len([line for line in err.splitlines() if line.strip()]) == 1, err


# -- 9: a control period the watchdog cannot span ----------------------------------------------


@pytest.mark.parametrize(
    ("extra", "culprit"),
    [(["--period", "0.5"], "--period"), (["--period", "0.15"], "--period")],
)
def test_a_period_the_watchdog_cannot_span_is_refused_before_connecting(
    extra, culprit, capsys
) -> None:
    argv = ["--port", NO_ARM, "run", "--controller", "pid", "--target", *TARGET]
    assert main([*argv, "--seconds", "1", *extra]) == Exit.USAGE
    err = capsys.readouterr().err
    _one_clear_line(err)
    assert culprit in err and "--watchdog" in err and "SafetyConfig" not in err
    assert "no arm" not in err  # refused before the port was opened


def test_a_longer_watchdog_lets_the_same_period_through_to_the_port(capsys) -> None:
    argv = ["--port", NO_ARM, "--watchdog", "1.0", "run", "--controller", "pid"]
    assert main([*argv, "--target", *TARGET, "--seconds", "1", "--period", "0.5"]) == Exit.NO_ARM


def test_the_control_loop_refuses_a_period_its_watchdog_cannot_span() -> None:
    client = ArmClient(open_transport("loop://"), safety=SafetyConfig(watchdog_s=0.2))
    try:
        with pytest.raises(ValueError, match="watchdog"):
            ControlLoop(client, object(), 0.5)  # type: ignore[arg-type]
        ControlLoop(client, object(), 0.1)  # type: ignore[arg-type]  # two periods: fine
    finally:
        client.close(safe=False)


def test_the_watchdog_says_when_the_feedback_stopped_not_the_controller() -> None:
    w = Watchdog()
    w.note_sent([commands.current(E, 10.0)], now=1.0)
    # The arm's last state came at 0.99; the loop, paced by it, sent nothing after 1.0.
    reason, _ = w.expired(1.3, 0.2, lambda dev: 0.99) or ("", ())
    assert reason.startswith("feedback from E (0x05) stale for 0.300 s"), reason
    assert "feedback stopped" in reason and "no command for 0.300 s either" in reason
    assert "--watchdog" in for_operator(reason)


def test_the_watchdog_blames_the_controller_only_while_feedback_arrives() -> None:
    w = Watchdog()
    w.note_sent([commands.current(E, 10.0)], now=1.0)
    reason, _ = w.expired(1.3, 0.2, lambda dev: 1.28) or ("", ())
    assert reason.startswith("no command for 0.300 s"), reason
    assert "controller did not command" in reason and "feedback kept arriving" in reason
    assert "--watchdog" in for_operator(reason)


# -- 10: --record pointed at the arm's own port ------------------------------------------------


@pytest.fixture
def pty_port(tmp_path):
    """A pty standing for the arm's port, linked as reach-sim links one: (link, slave path,
    master fd); whatever the driver writes arrives on the master."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    link = tmp_path / "alpha5"
    link.symlink_to(path)
    os.set_blocking(master, False)
    yield str(link), path, master
    os.close(slave)
    os.close(master)


def _written(master: int) -> bytes:
    try:
        return os.read(master, 1 << 16)
    except (BlockingIOError, OSError):
        return b""


@pytest.mark.parametrize("command", ["run", "monitor"])
@pytest.mark.parametrize("which", ["device", "link", "null"])
def test_a_recording_at_the_arms_port_or_a_device_is_refused_before_anything_is_sent(
    pty_port, command, which, capsys
) -> None:
    link, device, master = pty_port
    record = {"device": device, "link": link, "null": os.devnull}[which]
    argv = ["--port", link, command, "--record", record]
    if command == "run":
        argv += ["--controller", "pid", "--target", *TARGET, "--seconds", "1"]
    else:
        argv += ["--seconds", "1"]
    assert main(argv) == Exit.USAGE
    err = capsys.readouterr().err
    _one_clear_line(err)
    assert "--record" in err and ("arm's port" in err if which != "null" else "device" in err)
    assert _written(master) == b""


def test_a_log_file_at_the_arms_port_is_refused(pty_port, capsys) -> None:
    link, device, master = pty_port
    assert main(["--port", link, "--log-file", device, "info"]) == Exit.USAGE
    err = capsys.readouterr().err
    _one_clear_line(err)
    assert "--log-file" in err and "arm's port" in err
    assert _written(master) == b""


# -- 11: corrupt weights files -----------------------------------------------------------------

SHIPPED = Path(__file__).resolve().parents[1] / "policy/controllers/weights/ddpg_actor"


def _copy_actor(tmp_path: Path) -> tuple[Path, dict]:
    npz = tmp_path / "actor.npz"
    shutil.copy(SHIPPED.with_suffix(".npz"), npz)
    meta = json.loads(SHIPPED.with_suffix(".json").read_text())
    npz.with_suffix(".json").write_text(json.dumps(meta))
    return npz, meta


def _arrays(npz: Path) -> dict[str, Any]:
    with np.load(npz) as data:
        return {k: data[k] for k in data.files}


def _corrupt(kind: str, tmp_path: Path) -> Path:
    npz, meta = _copy_actor(tmp_path)
    meta_path = npz.with_suffix(".json")
    if kind == "missing-key":
        del meta["observation"]
    elif kind == "json-list":
        meta = [meta]  # type: ignore[assignment]
    elif kind == "string-for-number":  # used only once the network runs: failed mid-run
        meta["observation"]["qdot_scale"] = "1.2"
    elif kind == "string-for-limits":
        meta["current_limits_mA"] = "600"
    elif kind == "nested-json":
        meta_path.write_text("[" * 100_000 + "]" * 100_000)
        return npz
    elif kind == "one-d-layer":
        arrays = _arrays(npz)
        arrays["W0"] = arrays["W0"][0]
        np.savez(npz, **arrays)
    elif kind == "truncated-npz":
        data = npz.read_bytes()
        npz.write_bytes(data[: len(data) // 2])
    elif kind == "nan-weights":
        arrays = _arrays(npz)
        arrays["W1"][0, 0] = np.nan
        np.savez(npz, **arrays)
    elif kind == "bad-provenance":
        meta["provenance"] = {"algorithm": "TD3"}
    meta_path.write_text(json.dumps(meta))
    return npz


CORRUPTIONS = [
    "missing-key",
    "json-list",
    "string-for-number",
    "string-for-limits",
    "nested-json",
    "one-d-layer",
    "truncated-npz",
    "nan-weights",
    "bad-provenance",
]


@pytest.mark.parametrize("kind", CORRUPTIONS)
def test_a_corrupt_weights_file_is_refused_at_load_with_one_line(kind, tmp_path, capsys) -> None:
    npz = _corrupt(kind, tmp_path)
    with pytest.raises(ValueError, match=re.escape(str(tmp_path))):
        ActorWeights.load(npz)
    argv = ["--port", NO_ARM, "run", "--controller", "ddpg", "--param", f"weights={npz}"]
    assert main([*argv, "--target", *TARGET, "--seconds", "1"]) == Exit.USAGE
    err = capsys.readouterr().err
    _one_clear_line(err)
    assert "ddpg" in err and str(tmp_path) in err


def test_the_shipped_weights_still_load_and_act() -> None:
    actor = ActorWeights.load(SHIPPED.with_suffix(".npz"))
    assert actor.forward(np.zeros(actor.observation.size)).shape == (4,)


# -- 11: crafted recordings to `inspect` -------------------------------------------------------


def _craft(path: Path, rows: list[list[float]], times: list[float], summary: str | None) -> None:
    """A recording shaped like `run --record`'s: each joint's [q, target] per step."""
    import rerun as rr

    from reach_driver.recording import TIMELINE_STEP, TIMELINE_TIME

    rec = rr.RecordingStream("reach-driver", recording_id=f"crafted-{path.name}")
    rec.save(str(path))
    for k, (row, t) in enumerate(zip(rows, times, strict=True)):
        rec.set_time(TIMELINE_TIME, duration=t)
        rec.set_time(TIMELINE_STEP, sequence=k)
        for j in "EDCB":
            rec.log(f"joints/{j}/position", rr.Scalars(row))
    if summary is not None:
        rec.log("run/summary", rr.TextDocument(summary), static=True)
    rec.flush()
    rec.disconnect()


def _strict_json(text: str) -> object:
    def refuse(token: str) -> object:
        raise AssertionError(f"bare {token} in JSON output")

    return json.loads(text, parse_constant=refuse)


STEADY = [[1.0 + 0.01 * k, 1.5] for k in range(20)]
SPACED = [0.05 * k for k in range(20)]


@pytest.mark.parametrize(
    ("kind", "rows", "times", "summary", "said"),
    [
        ("summary-not-json", STEADY, SPACED, "{not json", "summary"),
        ("summary-a-list", STEADY, SPACED, "[1, 2]", "summary"),
        ("summary-nested", STEADY, SPACED, "[" * 100_000 + "]" * 100_000, "summary"),
        ("ragged-rows", [[1.0, 1.5]] * 10 + [[1.0]] * 10, SPACED, None, "rows"),
    ],
)
def test_a_crafted_recording_is_one_clear_error(
    kind, rows, times, summary, said, tmp_path, capsys
) -> None:
    path = tmp_path / f"{kind}.rrd"
    _craft(path, rows, times, summary)
    for json_flag in ([], ["--json"]):
        assert main(["inspect", *json_flag, str(path)]) == Exit.FAILED
        captured = capsys.readouterr()
        _one_clear_line(captured.out + captured.err)
        assert "cannot read" in captured.out + captured.err and said in captured.out + captured.err


def test_a_recording_whose_steps_all_sit_at_t0_reads_without_metrics(tmp_path, capsys) -> None:
    path = tmp_path / "t0.rrd"
    _craft(path, STEADY, [0.0] * len(STEADY), None)
    assert main(["inspect", "--json", str(path)]) == Exit.OK
    data = _strict_json(capsys.readouterr().out)
    assert data["steps"] == 20 and "metrics" not in data  # type: ignore[index,operator]
    assert "no metrics" in str(data["notes"])  # type: ignore[index]
    assert main(["inspect", str(path)]) == Exit.OK
    assert "no metrics" in capsys.readouterr().out


def test_inspect_json_has_no_bare_nan_or_infinity(tmp_path, capsys) -> None:
    path = tmp_path / "nan.rrd"
    rows = [*STEADY[:-1], [float("nan"), 1.5]]
    _craft(path, rows, SPACED, json.dumps({"rmse": float("inf"), "note": float("nan")}))
    assert main(["inspect", "--json", str(path)]) == Exit.OK
    data = _strict_json(capsys.readouterr().out)
    assert data["final_position"][0] is None  # type: ignore[index]
    assert data["recorded_summary"] == {"rmse": None, "note": None}  # type: ignore[index]


# -- 11: hostile parameter and targets files ---------------------------------------------------


def _nested(path: Path) -> Path:
    path.write_text("[" * 100_000 + "]" * 100_000)
    return path


@pytest.mark.parametrize("kind", ["dev-zero", "fifo", "huge", "nested", "not-utf8"])
def test_reach_sim_params_that_never_end_or_nest_are_refused_unread(kind, tmp_path, capsys) -> None:
    from reach_sim_bridge.cli import main as sim_main

    if kind == "dev-zero":
        path = Path("/dev/zero")
    elif kind == "fifo":
        path = tmp_path / "fifo.json"
        os.mkfifo(path)  # opening it for reading would wait for a writer: never opened
    elif kind == "huge":
        path = tmp_path / "huge.json"
        with open(path, "wb") as f:
            f.truncate(2**30)  # 1 GB, sparse: was read whole (2.15 GB of memory)
    elif kind == "nested":
        path = _nested(tmp_path / "nested.json")
    else:
        path = tmp_path / "latin1.json"
        path.write_bytes(b'{"water_density": "\xe9"}')
    with pytest.raises(SystemExit) as exc:
        sim_main(["--no-pty", "--params", str(path)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1 and str(path) in errors[0], err
    unread = {"dev-zero": "not a regular file", "fifo": "not a regular file", "huge": "more than"}
    assert unread.get(kind, "") in errors[0]  # refused before reading, not after


def test_evaluate_targets_nested_past_the_recursion_limit_is_one_line(tmp_path, capsys) -> None:
    from policy.campaigns.evaluate_command import main as evaluate_main

    path = _nested(tmp_path / "targets.json")
    argv = ["--controller", "pid", "--targets", str(path), "--out", str(tmp_path / "o.json")]
    assert evaluate_main(argv) == 2
    err = capsys.readouterr().err
    _one_clear_line(err)
    assert "nested too deeply" in err and "targets" in err


def test_lambda_params_nested_past_the_recursion_limit_is_a_usage_error(tmp_path, capsys) -> None:
    path = _nested(tmp_path / "arm.json")
    argv = ["--port", NO_ARM, "run", "--controller", "lambda", "--param", f"params={path}"]
    assert main([*argv, "--target", *TARGET, "--seconds", "1"]) == Exit.USAGE
    err = capsys.readouterr().err
    _one_clear_line(err)
    assert "nested too deeply" in err
