"""Every relative link in the README and docs/ leads somewhere: the file exists and, for a
markdown page, the `#section` is one of its headings (as GitHub makes anchors of them)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = [
    ROOT / "README.md",
    ROOT / "CHANGELOG.md",
    ROOT / "reach_sim_bridge" / "model" / "README.md",
    *sorted((ROOT / "docs").glob("*.md")),
]
LINK = re.compile(r"\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.DOTALL | re.MULTILINE)
CODE = re.compile(r"`[^`\n]*`")


def anchor(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation but `-` and `_` dropped, spaces
    to `-`."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(text: str) -> set[str]:
    found: set[str] = set()
    seen: dict[str, int] = {}
    for heading in re.findall(r"^#+\s+(.+)$", FENCE.sub("", text), re.MULTILINE):
        name = anchor(heading)
        n = seen.get(name, 0)
        seen[name] = n + 1
        found.add(name if n == 0 else f"{name}-{n}")
    return found


def broken_links(page: Path, root: Path = ROOT) -> list[str]:
    text = page.read_text(encoding="utf-8")
    prose = CODE.sub("", FENCE.sub("", text))
    out = []
    for target in LINK.findall(prose):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
            continue
        path, _, section = target.partition("#")
        linked = (page.parent / path).resolve() if path else page
        if not linked.exists():
            out.append(f"{page.relative_to(root)}: {target}: no such file")
        elif section and linked.suffix == ".md":
            if section not in anchors(linked.read_text(encoding="utf-8")):
                out.append(f"{page.relative_to(root)}: {target}: no such section")
    return out


def test_every_link_in_the_readme_and_docs_leads_somewhere() -> None:
    assert len(PAGES) > 10
    broken = [b for page in PAGES for b in broken_links(page)]
    assert broken == []


def test_the_readme_links_the_pages_it_sends_readers_to() -> None:
    linked = set(LINK.findall(FENCE.sub("", (ROOT / "README.md").read_text(encoding="utf-8"))))
    for page in ("docs/usage.md", "docs/hil.md", "docs/architecture.md", "docs/results.md"):
        assert page in linked, page


def test_the_checker_sees_a_broken_link_and_a_missing_section(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text(
        "# Top\n\n## Step 1a. One `arm`, one client\n\n"
        "[ok](#step-1a-one-arm-one-client) [self](page.md#top) [gone](gone.md) "
        "[nowhere](#no-such) [web](https://example.org/x.md) `[code](gone.md)`\n"
        "```sh\n# Not a heading\n```\n[fenced](#not-a-heading)\n"
    )
    assert broken_links(page, tmp_path) == [
        "page.md: gone.md: no such file",
        "page.md: #no-such: no such section",
        "page.md: #not-a-heading: no such section",
    ]
