"""`pip install reach-stack` talks to an arm without the heavy libraries, and a feature that
needs one names the extra to install.

The base install is the codec, the driver and `reach-driver`, recordings, and the controllers
that need no solver or simulator (pid, ddpg, ddpg-distilled); MuJoCo comes with `[sim]`,
CasADi with `[mpc]`, torch and Gymnasium with `[train]`, Ray with `[scale]` (pyproject.toml).
The heavy libraries are installed here, so each check runs in a child process whose import
system refuses them (a `sys.meta_path` finder), as a base install would, and which writes down
every attempt to import one: the driver's paths must not even try.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import WATCHDOG_S

from protocol.extras import DISTRIBUTION, OPTIONAL_MODULES, MissingExtra, needs_extra

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "mujoco", "casadi", "gymnasium", "ray")

#: Run in the child before anything else: refuse the heavy modules, log each attempt to import
#: one (a line per attempt in $TRIED), then run `-c CODE`, the script or the module named, as
#: python does.
BLOCKER = """
import importlib.abc, os, runpy, sys

class Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in HEAVY:
            with open(os.environ["TRIED"], "a", encoding="utf-8") as log:
                log.write(name + "\\n")
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, Refuse())
if sys.argv[1] == "-c":
    sys.argv = ["-c", *sys.argv[2:]]
    exec(compile(CODE, "<string>", "exec"), {"__name__": "__main__"})
elif sys.argv[1].endswith(".py"):
    sys.argv = sys.argv[1:]
    sys.path.insert(0, os.path.dirname(sys.argv[0]))
    runpy.run_path(sys.argv[0], run_name="__main__")
else:
    sys.argv = [sys.argv[1], *sys.argv[2:]]
    runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)
"""


def without_heavy(
    tmp_path: Path, *argv: str, code: str | None = None, refuse: tuple[str, ...] = HEAVY
) -> tuple[subprocess.CompletedProcess[str], list[str]]:
    """`python -m MODULE ARGV` (or `python -c code`) with the heavy libraries (or those in
    `refuse`) refused; the finished process and the refused modules it tried to import."""
    tried = tmp_path / "tried.txt"
    tried.write_text("")
    script = tmp_path / "blocked.py"
    head = f"HEAVY = {refuse!r}\nCODE = {code!r}\n"
    script.write_text(head + BLOCKER)
    args = ["-c", *argv] if code is not None else list(argv)
    proc = subprocess.run(
        [sys.executable, str(script), *args],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(ROOT), "TRIED": str(tried)},
    )
    return proc, tried.read_text().split()


def one_error_line(proc: subprocess.CompletedProcess[str]) -> str:
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    return lines[0]


def test_the_driver_cli_imports_nothing_heavy(tmp_path) -> None:
    proc, tried = without_heavy(tmp_path, "reach_driver", "--help")
    assert proc.returncode == 0, proc.stderr
    assert "usage: reach-driver" in proc.stdout
    assert tried == []


def test_pid_and_the_learned_controllers_act_without_heavy_libraries(tmp_path) -> None:
    code = """
import numpy as np
from reach_driver.controllers import ControlState, load_controller
state = ControlState(q=np.array([3.0, 1.5, 1.5, 1.5]), qdot=np.zeros(4), t=0.0)
for name in ("pid", "ddpg", "ddpg-distilled", "ddpg-distilled-pure"):
    ctrl = load_controller(name)
    ctrl.reset()
    print(name, *ctrl.act(state, np.array([3.2, 1.4, 1.6, 1.7])))
"""
    proc, tried = without_heavy(tmp_path, code=code)
    assert proc.returncode == 0, proc.stderr
    assert tried == []
    currents = {
        line.split()[0]: np.array(line.split()[1:], float) for line in proc.stdout.splitlines()
    }
    assert set(currents) == {"pid", "ddpg", "ddpg-distilled", "ddpg-distilled-pure"}
    for name, out in currents.items():
        assert out.shape == (4,) and np.all(np.isfinite(out)), (name, out)
    assert np.all(np.sign(currents["pid"]) == np.sign([0.2, -0.1, 0.1, 0.2]))


def test_controllers_lists_what_is_installed_and_what_each_missing_one_needs(tmp_path) -> None:
    proc, _ = without_heavy(tmp_path, "reach_driver", "controllers")
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    rows = {line.split()[0]: line for line in proc.stdout.splitlines() if line[:1].isalpha()}
    for name in ("pid", "ddpg", "ddpg-distilled", "ddpg-distilled-pure"):
        assert "not installed" not in rows[name] and "failed" not in rows[name], rows[name]
    assert rows["mpc"].split(None, 2)[2] == "(not installed: needs the mpc extra)"
    assert rows["lambda"].split(None, 2)[2] == "(not installed: needs the sim extra)"
    assert "    missing: the mpc controller needs CasADi: pip install 'reach-stack[mpc]'" in (
        proc.stdout.splitlines()
    )
    proc, _ = without_heavy(tmp_path, "reach_driver", "controllers", "--json")
    assert proc.returncode == 0, proc.stderr
    by_name = {info["name"]: info for info in json.loads(proc.stdout)}
    assert by_name["mpc"]["extra"] == "mpc" and by_name["lambda"]["extra"] == "sim"
    assert by_name["ddpg"]["extra"] is None and by_name["ddpg"]["provenance"]["complete"]
    assert by_name["lambda"]["error"] == (
        "the lambda controller needs MuJoCo: pip install 'reach-stack[sim]'"
    )


@pytest.mark.parametrize(
    ("controller", "expected"),
    [
        ("mpc", "error: the mpc controller needs CasADi: pip install 'reach-stack[mpc]'"),
        ("lambda", "error: the lambda controller needs MuJoCo: pip install 'reach-stack[sim]'"),
    ],
)
def test_a_controller_whose_extra_is_missing_is_one_line_and_exit_2(
    tmp_path, controller, expected
) -> None:
    argv = ["--port", str(tmp_path / "no-arm"), "run", "--controller", controller]
    argv += ["--target", "3", "1", "1", "1", "--seconds", "1"]
    proc, _ = without_heavy(tmp_path, "reach_driver", *argv)
    assert proc.returncode == 2
    assert one_error_line(proc) == expected


def test_reach_sim_without_mujoco_is_one_line_and_exit_2(tmp_path) -> None:
    proc, _ = without_heavy(tmp_path, "reach_sim_bridge", "--link", str(tmp_path / "arm"))
    assert proc.returncode == 2
    assert one_error_line(proc) == (
        "reach-sim: error: reach-sim (the virtual arm) needs MuJoCo: pip install 'reach-stack[sim]'"
    )
    assert not (tmp_path / "arm").exists()


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (
            ["tools/train.py", "--help"],
            "tools/train.py needs Gymnasium: pip install 'reach-stack[train]'",
        ),
        (
            ["tools/sweep.py", "--help"],
            "tools/sweep.py needs Gymnasium: pip install 'reach-stack[train]'",
        ),
        (["tools/demo.py", "--help"], "tools/demo.py needs MuJoCo: pip install 'reach-stack[sim]'"),
        (
            ["tools/evaluate.py", "--controller", "pid", "--random", "1", "--out", "x.json"],
            "tools/evaluate.py needs MuJoCo: pip install 'reach-stack[sim]'",
        ),
    ],
)
def test_a_tool_whose_extra_is_missing_is_one_line_and_exit_2(tmp_path, argv, expected) -> None:
    """The first library missing is named; the extra brings it and the others the tool needs."""
    proc, _ = without_heavy(tmp_path, str(ROOT / argv[0]), *argv[1:])
    assert proc.returncode == 2
    assert one_error_line(proc) == f"error: {expected}"
    assert not (tmp_path / "x.json").exists()


@pytest.mark.slow
def test_a_recorded_run_and_its_inspection_import_nothing_heavy(sim, tmp_path) -> None:
    """The driver's whole path on the base install: connect, run the learned controller with a
    recording, read the recording back (the arm is served by this process, which has MuJoCo)."""
    target = sim.snapshot().q + np.array([0.2, -0.1, 0.1, 0.2])
    record = tmp_path / "run.rrd"
    argv = ["--port", str(sim.link), "--watchdog", str(WATCHDOG_S), "run", "--controller", "ddpg"]
    argv += ["--target", *map(str, target), "--seconds", "1", "--record", str(record), "-q"]
    proc, tried = without_heavy(tmp_path, "reach_driver", *argv, "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["steps"] > 0
    assert tried == []
    proc, tried = without_heavy(tmp_path, "reach_driver", "inspect", str(record), "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["steps"] > 0
    assert tried == []


def test_export_to_mcap_without_its_extra_names_it_and_csv_needs_none(tmp_path) -> None:
    """The recording is not even read: the line comes at once, and no file is made."""
    from reach_driver.recording import RunRecorder, StepSample

    record = tmp_path / "run.rrd"
    with RunRecorder(record) as rec:
        for k in range(3):
            rec.log_step(StepSample(0.05 * k, k, np.ones(4), np.zeros(4), np.ones(4), np.zeros(4)))
    mcap = ("mcap", *HEAVY)
    argv = ["export", str(record), "--to", str(tmp_path / "run.mcap")]
    proc, tried = without_heavy(tmp_path, "reach_driver", *argv, refuse=mcap)
    assert proc.returncode == 2
    assert one_error_line(proc) == (
        "error: reach-driver export to .mcap needs the mcap library: "
        "pip install 'reach-stack[export]'"
    )
    assert tried == ["mcap"] and not (tmp_path / "run.mcap").exists()
    for suffix in ("csv", "parquet"):
        argv = ["export", str(record), "--to", str(tmp_path / f"run.{suffix}")]
        proc, tried = without_heavy(tmp_path, "reach_driver", *argv, refuse=mcap)
        assert proc.returncode == 0, proc.stderr
        assert tried == [] and (tmp_path / f"run.{suffix}").stat().st_size > 0


# -- the extras themselves (pyproject.toml) --------------------------------------------------


def _project() -> dict[str, Any]:
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    with (ROOT / "pyproject.toml").open("rb") as f:
        project: dict[str, Any] = tomllib.load(f)["project"]
    return project


def _name(requirement: str) -> str:
    """The distribution a requirement names, without extras, version or marker."""
    for stop in "[<>=!~;, ":
        requirement = requirement.split(stop, 1)[0]
    return requirement.strip().lower()


def _closure(extras: dict[str, list[str]], extra: str) -> set[str]:
    """Every distribution `extra` brings, through the extras of reach-stack it names."""
    found: set[str] = set()
    for requirement in extras[extra]:
        name = _name(requirement)
        if name == DISTRIBUTION:
            inner = requirement.split("[", 1)[1].split("]", 1)[0]
            for other in inner.split(","):
                found |= _closure(extras, other.strip())
        else:
            found.add(name)
    return found


def test_the_base_install_has_no_heavy_library_and_each_extra_brings_its_own() -> None:
    project = _project()
    base = {_name(r) for r in project["dependencies"]}
    assert base.isdisjoint({"torch", "mujoco", "casadi", "gymnasium", "ray"}), base
    assert {"numpy", "pyserial", "python-can", "rerun-sdk", "rich"} <= base
    extras: dict[str, list[str]] = project["optional-dependencies"]
    assert _closure(extras, "sim") == {"mujoco"}
    assert _closure(extras, "mpc") == {"mujoco", "casadi"}
    assert _closure(extras, "train") == {"mujoco", "torch", "gymnasium"}
    assert _closure(extras, "scale") == {"mujoco", "ray"}
    assert _closure(extras, "export") == {"mcap"}
    roles = ("sim", "mpc", "train", "scale", "export")
    assert _closure(extras, "all") == set().union(*(_closure(extras, r) for r in roles))
    assert set(OPTIONAL_MODULES) == {*HEAVY, "mcap"}  # each one an extra brings
    assert {"dev", "bench"} <= set(extras)


def test_every_extra_the_code_names_is_one_pyproject_defines() -> None:
    """A `needs_extra(feature, "x")` naming an extra that does not exist would tell the user
    to install something pip cannot find."""
    extras = set(_project()["optional-dependencies"])
    named: dict[str, object] = {}
    for package in ("protocol", "reach_driver", "reach_sim_bridge", "policy"):
        for path in (ROOT / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if (
                    isinstance(node, ast.Call)
                    and getattr(node.func, "id", None) == "needs_extra"
                    and len(node.args) == 2
                    and isinstance(node.args[1], ast.Constant)
                ):
                    named[f"{path.relative_to(ROOT)}:{node.lineno}"] = node.args[1].value
    assert named, "no needs_extra calls found"
    assert {where: extra for where, extra in named.items() if extra not in extras} == {}


def test_needs_extra_names_the_extra_for_an_optional_library_only() -> None:
    with pytest.raises(MissingExtra) as caught:
        with needs_extra("the mpc controller", "mpc"):
            raise ModuleNotFoundError("No module named 'casadi.casadi'", name="casadi.casadi")
    assert str(caught.value) == "the mpc controller needs CasADi: pip install 'reach-stack[mpc]'"
    assert caught.value.extra == "mpc" and isinstance(caught.value, ModuleNotFoundError)
    with pytest.raises(ModuleNotFoundError) as bug:  # not an optional library: a bug, as it is
        with needs_extra("the mpc controller", "mpc"):
            import no_such_module_of_ours  # type: ignore[import-not-found]  # noqa: F401
    assert not isinstance(bug.value, MissingExtra)
    with pytest.raises(MissingExtra) as outer:  # the feature asked for is the one named
        with needs_extra("reach-sim (the virtual arm)", "sim"):
            with needs_extra("the arm model", "other"):
                raise ModuleNotFoundError("No module named 'mujoco'", name="mujoco")
    assert outer.value.extra == "sim" and str(outer.value).startswith("reach-sim (the virtual")
