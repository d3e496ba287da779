"""The packages stay ignorant of the ones above them in the loop (see docs/architecture.md)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
OURS = {"protocol", "reach_driver", "reach_sim_bridge", "policy"}
ALLOWED = {
    "protocol": set(),
    "reach_sim_bridge": {"protocol"},
    "reach_driver": {"protocol"},
    "policy": {"protocol", "reach_sim_bridge", "reach_driver"},
}


def _imported_packages(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module.split(".")[0])
    return found & OURS


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_package_imports_only_what_is_below_it(package: str) -> None:
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"{package} has no modules"
    offending = {
        str(f.relative_to(ROOT)): sorted(_imported_packages(f) - ALLOWED[package] - {package})
        for f in files
    }
    offending = {k: v for k, v in offending.items() if v}
    assert not offending, f"{package} imports packages above it: {offending}"


def test_checker_sees_a_forbidden_import(tmp_path: Path) -> None:
    bad = tmp_path / "m.py"
    bad.write_text("import reach_sim_bridge.arm\nfrom policy import pid\n")
    assert _imported_packages(bad) == {"reach_sim_bridge", "policy"}
