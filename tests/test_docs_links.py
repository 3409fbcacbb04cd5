"""The docs' relative links reach files that exist, and their ``#anchors`` reach headings of the linked page.

Anchors follow GitHub's rule for headings: markdown links and code/emphasis marks dropped, lower case, every
character that is not a letter, digit, ``_``, ``-`` or space removed, spaces turned into ``-``, a repeated heading
suffixed ``-1``, ``-2``, ... Fenced code blocks are skipped on both sides.
"""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

import pytest

from tests.test_docs_commands import DOCS, ROOT

FENCE = re.compile(r"```.*?```", re.S)


def heading_anchors(markdown: str) -> set[str]:
    """The anchors GitHub gives the headings of a markdown text."""
    seen: Counter = Counter()
    anchors = set()
    for heading in re.findall(r"^#{1,6} +(.+?) *#*$", FENCE.sub("", markdown), re.M):
        text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).replace("`", "").replace("*", "")
        slug = re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")
        anchors.add(f"{slug}-{seen[slug]}" if seen[slug] else slug)
        seen[slug] += 1
    return anchors


def broken_links(doc: Path) -> list[str]:
    """``target (why)`` of each relative link of ``doc`` whose file or anchor does not exist."""
    bad = []
    for target in re.findall(r"\]\(([^)\s]+)\)", FENCE.sub("", doc.read_text(encoding="utf-8"))):
        if re.match(r"[a-z]+:", target):  # http://, https://, mailto:
            continue
        path, _, anchor = target.partition("#")
        linked = (doc.parent / path).resolve() if path else doc
        if not linked.exists():
            bad.append(f"{target} (no such file)")
        elif anchor and linked.suffix == ".md" and anchor not in heading_anchors(linked.read_text(encoding="utf-8")):
            bad.append(f"{target} (no such heading)")
    return bad


def test_heading_anchors_follow_githubs_rule():
    text = ("# Results (measured 2026-11-25, commit e97f618)\n## The `--int8` graph: ≤ 150 ms\n"
            "## [Linked](x.md) *title*\n## Results (measured 2026-11-25, commit e97f618)\n```\n# not a heading\n```\n")
    assert heading_anchors(text) == {"results-measured-2026-11-25-commit-e97f618", "the---int8-graph--150-ms",
                                     "linked-title", "results-measured-2026-11-25-commit-e97f618-1"}


def test_a_broken_link_is_found(tmp_path):
    (tmp_path / "b.md").write_text("# Against the RVT-T default (2026-11-25)\n")
    doc = tmp_path / "a.md"
    doc.write_text("[ok](b.md#against-the-rvt-t-default-2026-11-25) [old](b.md#against-the-rvt-t-default-renamed) "
                   "[gone](c.md) [web](https://example.org/x#y)\n")
    assert broken_links(doc) == ["b.md#against-the-rvt-t-default-renamed (no such heading)", "c.md (no such file)"]


@pytest.mark.parametrize("doc", DOCS, ids=[str(d.relative_to(ROOT)) for d in DOCS])
def test_doc_links_resolve(doc):
    assert not broken_links(doc), f"{doc.relative_to(ROOT)}: broken links: {broken_links(doc)}"
