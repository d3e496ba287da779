"""tools/attack.py runs every attack at a small scale, and every one holds."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: the tool runs this tree's packages, whatever is installed
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def test_every_attack_holds_at_a_small_scale(tmp_path: Path) -> None:
    out = tmp_path / "attacks.json"
    cmd = [sys.executable, str(ROOT / "tools" / "attack.py"), "--scale", "0.05", "--json", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT, env=ENV)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    outcomes = json.loads(out.read_text())
    assert {o["attack"] for o in outcomes} >= {"codec-fuzz", "udp-stranger", "watchdog"}
    assert all(o["held"] for o in outcomes), outcomes
    assert "| attack | count | result | held |" in proc.stdout


def test_a_bad_scale_is_refused() -> None:
    cmd = [sys.executable, str(ROOT / "tools" / "attack.py"), "--scale", "-1"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=ROOT, env=ENV)
    assert proc.returncode == 2 and "--scale" in proc.stderr
