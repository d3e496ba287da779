"""The repository stands alone: nothing in it reads or cites files outside it.

A user clones it anywhere with nothing beside it, so no code, test or doc may point at a
sibling folder of background material or at a path of the machine it was written on.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SKIP_DIRS = {
    ".git",
    ".venv",
    "__pycache__",
    ".mypy_cache",
    ".ruff_cache",
    ".pytest_cache",
    ".hypothesis",
    "runs",
    "out",
    "build",
    "dist",
}
TEXT_SUFFIXES = {".py", ".md", ".toml", ".xml", ".json", ".txt", ".cfg", ".yml", ".yaml", ""}
# Built from pieces so this file does not match itself.
FORBIDDEN = re.compile(
    "|".join(
        [
            re.escape("../" + "shared"),
            re.escape("shared" + "/reference"),
            "REACH_" + "SHARED",
            re.escape("/work" + "/"),
            r"(?<![\w/.-])/home/\w+",
            # The background notes by name: their facts live in docs/ and model/README.md.
            r"\b(alpha5-model|bravo7-model|bpl-protocol|paper-benchmark|tooling-notes)"
            + re.escape(".md"),
        ]
    )
)


def _text_files() -> list[Path]:
    files = []
    for path in ROOT.rglob("*"):
        rel = path.relative_to(ROOT)
        if any(part in SKIP_DIRS or part.endswith(".egg-info") for part in rel.parts):
            continue
        if path.is_file() and path.suffix in TEXT_SUFFIXES and path.stat().st_size < 2_000_000:
            files.append(path)
    return files


def test_nothing_cites_a_path_outside_the_repository() -> None:
    hits = []
    for path in _text_files():
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for n, line in enumerate(text.splitlines(), 1):
            if FORBIDDEN.search(line):
                hits.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()[:100]}")
    assert not hits, "files refer to paths outside the repository:\n" + "\n".join(hits)


def test_the_checker_sees_an_outside_path() -> None:
    assert FORBIDDEN.search("see " + "../" + "shared" + "/x.md")
    assert FORBIDDEN.search("cited from /work" + "/main/docs")
    assert FORBIDDEN.search("(alpha5" + "-model.md)")
    assert not FORBIDDEN.search("docs/protocol.md and reach_sim_bridge/model/README.md")
