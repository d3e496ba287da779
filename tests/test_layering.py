"""Each layer stays ignorant of the ones above it in the loop (see docs/architecture.md).

A layer is a package or one of its concern subpackages. The arm's model sits below both the
emulator and the controllers, so a controller that needs a twin never imports the emulator; the
driver imports nothing but the protocol.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("protocol", "reach_driver", "reach_sim_bridge", "policy")
MODEL = "reach_sim_bridge.model"
FIT = "reach_sim_bridge.fit"
EMULATOR = "reach_sim_bridge.emulator"
CONTROLLERS = "policy.controllers"
TASKS = "policy.tasks"
RL = "policy.rl"
CAMPAIGNS = "policy.campaigns"
ALLOWED: dict[str, set[str]] = {
    "protocol": set(),
    "reach_driver": {"protocol"},
    MODEL: {"protocol"},
    FIT: {"protocol", MODEL},
    EMULATOR: {"protocol", MODEL},
    "reach_sim_bridge": {"protocol", MODEL, EMULATOR},  # the `reach-sim` command
    CONTROLLERS: {"protocol", "reach_driver", MODEL},
    TASKS: {"protocol", "reach_driver", MODEL, CONTROLLERS},
    RL: {"protocol", "reach_driver", MODEL, CONTROLLERS, TASKS},
    CAMPAIGNS: {"protocol", "reach_driver", MODEL, FIT, EMULATOR, CONTROLLERS, TASKS, RL},
    "policy": set(),  # the package's own __init__ holds nothing
}


def layer_of(module: str) -> str | None:
    """The most specific layer a dotted module name belongs to (None: not ours)."""
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        name = ".".join(parts[:n])
        if name in ALLOWED:
            return name
    return None


def _imported_layers(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            # `from reach_sim_bridge import cli` names the module `reach_sim_bridge.cli`
            names = [f"{node.module}.{alias.name}" for alias in node.names]
        else:
            continue
        found.update(layer for name in names if (layer := layer_of(name)) is not None)
    return found


def _layer_files(layer: str) -> list[Path]:
    folder = ROOT / layer.replace(".", "/")
    inner = {name for name in ALLOWED if name.startswith(layer + ".")}
    return [
        f
        for f in sorted(folder.rglob("*.py"))
        if layer_of(".".join(f.relative_to(ROOT).with_suffix("").parts)) == layer
        and not any(f.is_relative_to(ROOT / n.replace(".", "/")) for n in inner)
    ]


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_layer_imports_only_what_is_below_it(layer: str) -> None:
    files = _layer_files(layer)
    assert files, f"{layer} has no modules"
    offending = {
        str(f.relative_to(ROOT)): sorted(_imported_layers(f) - ALLOWED[layer] - {layer})
        for f in files
    }
    offending = {k: v for k, v in offending.items() if v}
    assert not offending, f"{layer} imports layers above it: {offending}"


def test_every_module_is_in_a_layer() -> None:
    for package in PACKAGES:
        for f in (ROOT / package).rglob("*.py"):
            module = ".".join(f.relative_to(ROOT).with_suffix("").parts)
            assert layer_of(module) is not None, module


def test_checker_sees_a_forbidden_import(tmp_path: Path) -> None:
    bad = tmp_path / "m.py"
    bad.write_text(
        "import reach_sim_bridge.emulator.server\n"
        "from policy import campaigns\n"
        "from reach_sim_bridge.model.arm import Alpha5Arm\n"
        "import numpy\n"
    )
    assert _imported_layers(bad) == {EMULATOR, CAMPAIGNS, MODEL}
