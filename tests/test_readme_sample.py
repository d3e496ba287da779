"""README.md's sample output is what its command prints today (tools/readme_sample.py): run
against the virtual arm, same lines, words and columns, numbers within the tool's tolerance."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from conftest import WATCHDOG_S
from test_docs_commands import sh_commands

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import readme_sample  # noqa: E402

README = ROOT / "README.md"


@pytest.mark.slow
def test_the_readme_sample_is_what_its_command_prints_now(arm_pauses_with_host: None) -> None:
    """The run is the README's command at real time (as `reach-sim` serves the arm), with a
    watchdog a loaded host does not trip (the output is the same unless it trips)."""
    sample = readme_sample.read_sample(README.read_text(encoding="utf-8"))
    ran = readme_sample.run_sample(sample.command, ["--watchdog", str(WATCHDOG_S)])
    assert readme_sample.differences(sample.lines, ran) == [], "run `make readme-sample`"


def test_the_sample_command_is_one_the_readme_tells_the_user_to_type() -> None:
    """So tests/test_docs_commands.py runs it too, and the sample shows what the reader ran."""
    sample = readme_sample.read_sample(README.read_text(encoding="utf-8"))
    assert sample.command in sh_commands(README)
    assert readme_sample.ELIDED in sample.lines  # the host's timing is left out, and said so
    assert not any(line.startswith(readme_sample.HOST_LINES) for line in sample.lines)


SHOWN = [
    "run: 100 steps, 5.00 s loop time",
    "    E        4.0000       4.0021      -0.0021",
    "...",
    "energy [J]                     4.58  energy_j",
    "reached                         yes  reached",
    "overshoot: D went 6.4 mrad (2.21 % of its step) past its goal at 3.40 s",
]


def test_a_run_within_the_tolerance_holds() -> None:
    ran = list(SHOWN)
    ran[0] = "run: 99 steps, 5.00 s loop time"  # a tick lost to a loaded host
    ran[1] = "    E        4.0000       4.0032      -0.0032"  # columns realigned too
    ran[3] = "energy [J]                   5.9  energy_j"  # energy: a host pause early
    assert readme_sample.differences(SHOWN, ran) == []


@pytest.mark.parametrize(
    ("line", "now", "named"),
    [
        (3, "energy [J]                     7.5  energy_j", "4.58 shown, 7.5 now"),
        (5, SHOWN[5].replace("6.4 mrad", "9.0 mrad"), "6.4 shown, 9.0 now"),
        (4, "reached                          no  reached", "line 5"),  # a word changed
        (5, "overshoot: B went 6.4 mrad (2.21 % of its step) past its goal at 3.40 s", "line 6"),
        (3, "energy [J]   4.58  energy_j  4.1", "line 4"),  # a column more
        (0, "run: 100 steps", "line 1"),  # a figure fewer
    ],
)
def test_a_stale_sample_is_named(line: int, now: str, named: str) -> None:
    ran = list(SHOWN)
    ran[line] = now
    found = readme_sample.differences(SHOWN, ran)
    assert len(found) == 1 and named in found[0], found


def test_lines_added_or_missing_are_named() -> None:
    assert readme_sample.differences(SHOWN, [*SHOWN, "a new line"]) == [
        "1 lines printed now, not shown, from: 'a new line'"
    ]
    assert "shown, not printed now" in readme_sample.differences(SHOWN, SHOWN[:-1])[0]


def test_host_lines_are_elided_once_per_run() -> None:
    printed = "run: 1 steps\nrate 20 Hz\nsaturated steps 0\nmetrics\ntorque = x\narm left in y\n"
    assert readme_sample.abridged(printed) == [
        "run: 1 steps",
        "...",
        "metrics",
        "...",
        "arm left in y",
    ]


def test_writing_replaces_the_block_and_nothing_else(tmp_path: Path) -> None:
    text = README.read_text(encoding="utf-8")
    sample = readme_sample.read_sample(text)
    fresh = readme_sample.Sample(sample.command, ["run: 1 steps", "...", "arm left in y"])
    written = readme_sample.with_sample(text, fresh)
    assert readme_sample.read_sample(written) == fresh
    head, tail = text.split(readme_sample.BEGIN)[0], text.split(readme_sample.END)[1]
    assert written.startswith(head) and written.endswith(tail)
    assert readme_sample.with_sample(written, sample) == text  # and back, byte for byte


def test_a_readme_without_the_block_is_one_clear_error(tmp_path: Path, capsys) -> None:
    readme = tmp_path / "README.md"
    readme.write_text("# nothing here\n")
    assert readme_sample.main(["--readme", str(readme)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("readme_sample: README.md needs exactly one") and err.count("\n") == 1
