"""The README and docs/ link to each other and to benchmark results by relative paths and section anchors:
every such link must reach an existing file and, where it names one, an existing heading."""
from __future__ import annotations

import functools
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")


@functools.cache
def _anchors(path: Path) -> set[str]:
    """GitHub's anchors for the headings of a Markdown file (outside code fences)."""
    anchors, fenced = set(), False
    for line in path.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and re.match(r"#+ ", line):
            title = line.lstrip("#").strip().lower()
            anchors.add(re.sub(r"[^\w\- ]", "", title).replace(" ", "-"))
    return anchors


def _links(path: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)  # links in code blocks are code
    return [t for t in LINK.findall(text) if not re.match(r"[a-z]+:", t)]


def test_the_docs_are_found():
    names = {p.relative_to(REPO).as_posix() for p in DOCS}
    assert {"README.md", "docs/usage.md", "docs/results/measured.md", "docs/results/pretraining.md",
            "docs/results/finetuning.md", "docs/results/shortfalls.md"} <= names


def _broken(doc: Path) -> list[str]:
    """``doc``'s relative links that reach no file, or no heading of the Markdown file they name."""
    broken = []
    for target in _links(doc):
        path, _, anchor = target.partition("#")
        dest = (doc.parent / path).resolve() if path else doc
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target}: no such heading in {dest.name}")
    return broken


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.relative_to(REPO).as_posix())
def test_every_relative_link_reaches_a_file_and_its_heading(doc):
    broken = _broken(doc)
    assert not broken, f"{doc.relative_to(REPO)}: " + "; ".join(broken)


def test_a_broken_link_and_a_missing_heading_are_caught(tmp_path):
    doc = tmp_path / "a.md"
    doc.write_text("# Title\n\n[ok](#title) [gone](b.md) [bad](#nowhere)\n\n```\n[in code](c.md)\n```\n")
    assert _links(doc) == ["#title", "b.md", "#nowhere"]
    assert _anchors(doc) == {"title"}
    assert _broken(doc) == ["b.md: no such file", "#nowhere: no such heading in a.md"]
