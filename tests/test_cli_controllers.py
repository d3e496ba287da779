"""`reach-driver controllers`: every registered controller, what it is, and how a learned one was
trained, as a table in 80 columns or as JSON; a plugin that fails to load is listed, not fatal."""

from __future__ import annotations

import argparse
import json
import re
import sys
import types
from collections.abc import Callable
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any

import pytest

from reach_driver import controllers
from reach_driver.cli import Exit, main
from reach_driver.controllers import GROUP, learned

ROOT = Path(__file__).resolve().parents[1]


def registered() -> set[str]:
    """The names pyproject.toml registers in the controllers' entry-point group (read as text:
    tomllib is Python 3.11+)."""
    text = (ROOT / "pyproject.toml").read_text()
    section = text.split(f'[project.entry-points."{GROUP}"]', 1)[1].split("\n[", 1)[0]
    lines = [line for line in section.splitlines() if "=" in line and not line.startswith("#")]
    return {line.split("=", 1)[0].strip() for line in lines}


def listing(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    assert main(["controllers", *argv]) == Exit.OK
    captured = capsys.readouterr()
    assert "Traceback" not in captured.out + captured.err
    return captured.out


def rows(text: str) -> dict[str, list[str]]:
    """Each table row's cells by controller name (rows start in column 0)."""
    lines = text.splitlines()[1:]
    return {line.split()[0]: line.split(None, 2) for line in lines if not line.startswith(" ")}


def with_entry_point(monkeypatch: pytest.MonkeyPatch, name: str, value: str) -> None:
    """The installed entry points plus one more, as if another package registered it."""
    real = controllers.entry_points

    def lookup(*, group: str) -> list[EntryPoint]:
        return [*real(group=group), EntryPoint(name, value, group)]

    monkeypatch.setattr(controllers, "entry_points", lookup)


def test_the_table_lists_every_registered_controller_in_80_columns(capsys) -> None:
    text = listing(capsys)
    assert text.splitlines()[0].split() == ["name", "kind", "summary"]
    table = rows(text)
    assert set(table) == registered()
    assert all(len(line) <= 80 for line in text.splitlines()), text
    for name in ("pid", "mpc", "lambda"):
        assert table[name][1] == "engineered" and "no learning" in table[name][2], table[name]
    for name in ("ddpg-distilled", "ddpg-distilled-pure"):
        assert table[name][1] == "learned", table[name]
    block = text.split("\nddpg-distilled ", 1)[1].split("\nddpg-distilled-pure ", 1)[0]
    assert "    teacher: PDExpert (privileged: true state" in block
    assert "    demonstrations: 100 episodes" in block
    assert "    stages: 4 (each in --json)" in block


def test_json_gives_the_distilled_controllers_provenance(capsys) -> None:
    infos = json.loads(listing(capsys, "--json"))
    by_name = {info["name"]: info for info in infos}
    assert set(by_name) == registered()
    assert all(info["error"] is None for info in infos), infos
    distilled = by_name["ddpg-distilled"]
    assert distilled["target"] == "policy.controllers.ddpg_distilled:make_controller"
    assert distilled["kind"] == "learned" and distilled["summary"].startswith("TD3+BC actor")
    provenance = distilled["provenance"]
    assert provenance["demonstrations"] != "none" and "expert" in provenance["teacher"].lower()
    assert provenance["env_steps"] == sum(stage["env_steps"] for stage in provenance["stages"])
    assert "reference integral" in provenance["around_the_network"]
    assert by_name["ddpg-distilled-pure"]["provenance"]["around_the_network"].startswith("nothing")
    for name in ("pid", "mpc", "lambda"):
        assert by_name[name]["kind"] == "engineered" and by_name[name]["provenance"] is None


def test_json_says_ddpg_was_learned_from_scratch(capsys) -> None:
    by_name = {info["name"]: info for info in json.loads(listing(capsys, "--json"))}
    ddpg = by_name["ddpg"]
    assert ddpg["target"] == "policy.controllers.ddpg:make_controller"
    assert ddpg["kind"] == "learned" and "from scratch" in ddpg["summary"]
    provenance = ddpg["provenance"]
    assert provenance["demonstrations"] == "none" and provenance["teacher"] == "none"
    assert provenance["algorithm"] == "DDPG" and provenance["complete"]
    assert "tools/train.py" in provenance["command"] and provenance["env_steps"] > 0
    assert provenance["around_the_network"].startswith("nothing")


def test_a_controller_that_fails_to_import_is_listed_with_its_error(monkeypatch, capsys) -> None:
    with_entry_point(monkeypatch, "broken", "no_such_package_xyz.ctrl:make_controller")
    text = listing(capsys)
    assert rows(text)["broken"][2] == "(failed to load)"
    assert "    error: ModuleNotFoundError: No module named 'no_such_package_xyz'" in text
    assert set(rows(text)) == registered() | {"broken"}  # the others are still described
    infos = {info["name"]: info for info in json.loads(listing(capsys, "--json"))}
    assert infos["broken"]["error"].startswith("ModuleNotFoundError")
    assert infos["broken"]["provenance"] is None and infos["broken"]["summary"] == ""


def test_a_learned_controller_whose_provenance_fails_says_why(monkeypatch, capsys) -> None:
    def weights_gone() -> dict[str, Any]:
        raise FileNotFoundError("no actor weights at gone.npz")

    @learned(weights_gone)
    def make_controller(**kwargs: Any) -> Any:
        """An actor whose weights file went missing."""

    module = types.ModuleType("fake_learned_controller")
    module.make_controller = make_controller  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, module.__name__, module)
    with_entry_point(monkeypatch, "gone", f"{module.__name__}:make_controller")
    text = listing(capsys)
    assert rows(text)["gone"][1:] == ["learned", "An actor whose weights file went missing"]
    assert "    error: provenance: FileNotFoundError: no actor weights at gone.npz" in text


def test_help_says_a_broken_plugin_does_not_change_the_exit_status(capsys) -> None:
    with pytest.raises(SystemExit) as done:
        main(["controllers", "--help"])
    assert done.value.code == 0
    assert "exit status is still 0" in " ".join(capsys.readouterr().out.split())


def _controller_help(parser: argparse.ArgumentParser) -> str:
    (action,) = [a for a in parser._actions if "--controller" in a.option_strings]
    return action.help or ""


def _parsers() -> dict[str, Callable[[], argparse.ArgumentParser]]:
    from policy.campaigns.evaluate_command import build_parser as evaluate_parser
    from policy.campaigns.robustness.command import build_parser as robustness_parser
    from reach_driver.cli.parser import build_parser as driver_parser

    def run_parser() -> argparse.ArgumentParser:
        sub = [a for a in driver_parser()._actions if isinstance(a, argparse._SubParsersAction)]
        return sub[0].choices["run"]

    return {
        "reach-driver run": run_parser,
        "tools/evaluate.py": evaluate_parser,
        "tools/robustness.py": robustness_parser,
    }


@pytest.mark.parametrize(
    "program", ["reach-driver run", "tools/evaluate.py", "tools/robustness.py"]
)
def test_each_help_names_the_registered_controllers(program, monkeypatch) -> None:
    """--controller's help lists what is registered, read from the entry points: every shipped
    controller, and one another package registers, with no hand-kept list to go stale."""
    named = set(re.findall(r"[\w-]+", _controller_help(_parsers()[program]())))
    assert registered() <= named, f"{program} --help leaves out {registered() - named}"
    with_entry_point(monkeypatch, "someone-elses", "their_package.ctrl:make_controller")
    assert "someone-elses" in _controller_help(_parsers()[program]())
