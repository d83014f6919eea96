"""The README and the pages of docs/ hold together: every relative link reaches a file and every
#anchor a heading (GitHub's rule: lowercase, spaces to '-', punctuation dropped); every benchmark
figure a page states is a link to its section of benchmarks/RESULTS.md whose text appears in
that section, so no figure can go stale; and the README stays short.

A figure is written as a link, e.g. `[4 [4, 4]](../benchmarks/RESULTS.md#closed-loop-...)`: the
reader follows it to the run that measured it, and this test finds the text (bold and line
breaks aside) in that section. A median with its quartiles or a ratio written anywhere else on
a page fails the test.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "RESULTS.md"
PAGES = [ROOT / "README.md", ROOT / "ARCHITECTURE.md", *sorted((ROOT / "docs").glob("*.md"))]
README_LINES = 400
README_CELL = 200

FENCE = re.compile(r"^```.*?^```[ \t]*$", re.M | re.S)
HEADING = re.compile(r"^(#{1,6})[ \t]+(.+?)[ \t]*#*[ \t]*$", re.M)
# a median with its quartiles (`4 [4, 5]`) or a ratio (`×1.22`, `0.53×`)
FIGURE = re.compile(r"\d+(?:\.\d+)? \[\d+(?:\.\d+)?, \d+(?:\.\d+)?\]|×\s?\d+\.\d+|\d+\.\d+\s?×")


def _prose(text: str) -> str:
    """The text without its fenced code blocks (a line kept blank for each)."""
    return FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: its text (links and code marks dropped), lowercase,
    everything but letters, digits, spaces, '-' and '_' dropped, spaces to '-'."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = re.sub(r"[^\w\- ]", "", text.lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every anchor of a page, with GitHub's `-1`, `-2` … for repeated headings."""
    seen: dict[str, int] = {}
    result = set()
    for match in HEADING.finditer(_prose(path.read_text())):
        base = slug(match.group(2))
        count = seen.get(base, 0)
        seen[base] = count + 1
        result.add(base if count == 0 else f"{base}-{count}")
    return result


def links(text: str) -> list[tuple[str, str]]:
    """(text, target) of every inline link and image of a page's prose; a link's text may hold
    balanced brackets (`[4 [4, 5]](…)`)."""
    found = []
    prose = _prose(text)
    for match in re.finditer(r"\]\(([^()\s]*)\)", prose):
        depth, start = 0, match.start()
        while start >= 0:
            char = prose[start]
            depth += {"]": 1, "[": -1}.get(char, 0)
            if depth == 0:
                break
            start -= 1
        if start >= 0:
            found.append((prose[start + 1 : match.start()], match.group(1)))
    return found


def section(path: Path, anchor: str) -> str:
    """The text under the heading of `anchor` up to the next heading of its level or above."""
    text = _prose(path.read_text())
    headings = list(HEADING.finditer(text))
    for i, match in enumerate(headings):
        if slug(match.group(2)) == anchor:
            level = len(match.group(1))
            end = next(
                (h.start() for h in headings[i + 1 :] if len(h.group(1)) <= level), len(text)
            )
            return text[match.end() : end]
    raise AssertionError(f"{path.name} has no heading #{anchor}")


def _plain(text: str) -> str:
    return " ".join(text.replace("**", "").replace("`", "").split())


def _targets(page: Path) -> list[tuple[str, Path, str]]:
    """(link text, target file, anchor) of the page's links within the repository."""
    result = []
    for text, target in links(page.read_text()):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # https:, mailto: …
            continue
        path, _, anchor = target.partition("#")
        result.append((text, (page.parent / path).resolve() if path else page, anchor))
    return result


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(ROOT).as_posix() for p in PAGES])
def test_every_link_reaches_a_file_and_a_heading(page: Path) -> None:
    broken = []
    for text, path, anchor in _targets(page):
        if not path.exists():
            broken.append(f"[{text}] → {path.relative_to(ROOT)}: no such file")
        elif anchor and path.suffix == ".md" and anchor not in anchors(path):
            broken.append(f"[{text}] → {path.relative_to(ROOT)}#{anchor}: no such heading")
    assert not broken, "\n".join(broken)


def test_every_page_of_docs_is_linked_from_the_readme() -> None:
    linked = {path for _, path, _ in _targets(ROOT / "README.md")}
    orphans = [p.name for p in sorted((ROOT / "docs").glob("*.md")) if p not in linked]
    assert not orphans, f"pages the README does not link: {orphans}"


def _figure_links(page: Path) -> list[tuple[str, str]]:
    return [
        (text, anchor)
        for text, path, anchor in _targets(page)
        if path == RESULTS and re.search(r"\d", text)
    ]


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(ROOT).as_posix() for p in PAGES])
def test_every_figure_is_the_one_in_results(page: Path) -> None:
    stale = []
    for text, anchor in _figure_links(page):
        assert anchor, f"the figure [{text}] links RESULTS.md without naming its section"
        if _plain(text) not in _plain(section(RESULTS, anchor)):
            stale.append(f"{text!r} is not in RESULTS.md#{anchor}")
    assert not stale, "\n".join(stale)


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(ROOT).as_posix() for p in PAGES])
def test_no_figure_is_stated_outside_a_link(page: Path) -> None:
    prose = _prose(page.read_text())
    for text, _ in _figure_links(page):
        prose = prose.replace(text, "")
    prose = re.sub(r"`[^`\n]*`", "", prose)  # code spans: arguments, not figures
    unlinked = FIGURE.findall(prose)
    assert not unlinked, f"figures not linked to benchmarks/RESULTS.md: {unlinked}"


def test_the_pages_state_their_figures_as_links() -> None:
    assert sum(len(_figure_links(page)) for page in PAGES) >= 10


def test_the_readme_is_short() -> None:
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= README_LINES, f"README.md has {len(lines)} lines"
    long = [
        cell.strip()[:80]
        for line in _prose("\n".join(lines)).splitlines()
        if line.startswith("|")
        for cell in re.split(r"(?<!\\)\|", line.strip().strip("|"))
        if len(cell.strip()) > README_CELL
    ]
    assert not long, f"README table cells over {README_CELL} characters: {long}"


def test_the_slugs_follow_github() -> None:
    assert slug("The `archery` command") == "the-archery-command"
    assert slug("PoWER's scale (bench_power_scale)") == "powers-scale-bench_power_scale"
    assert slug("`archery help VERB`, `archery --version`") == "archery-help-verb-archery---version"
