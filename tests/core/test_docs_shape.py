"""The docs stay user docs (issue 47): no page over 500 lines (the training guide 400), no commit
hashes, no dated journal headings. A page that grows past its bound is split or cut, not let run."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]
MAX_LINES = {"detector-training.md": 400}
DEFAULT_MAX_LINES = 500

# A commit hash as the docs would quote it: 7 to 40 hex digits holding a letter and a digit. A
# file's digest written as `sha256=...` (the weights a result was made with) is not one.
HASH = re.compile(r"(?<![\w=+.-])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}(?![\w.-])")
DATED_HEADING = re.compile(r"^#+ .*\b20\d\d-\d\d(-\d\d)?\b", re.MULTILINE)


def test_the_pages_are_found():
    assert len(PAGES) > 10 and (ROOT / "docs" / "detector-training.md") in PAGES


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_a_page_keeps_its_length(page):
    lines = len(page.read_text(encoding="utf-8").splitlines())
    assert lines <= MAX_LINES.get(page.name, DEFAULT_MAX_LINES), f"{page.name}: {lines} lines"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_a_page_quotes_no_commit_hash_and_dates_no_section(page):
    text = page.read_text(encoding="utf-8")
    assert HASH.findall(text) == [], page.name
    assert DATED_HEADING.findall(text) == [], page.name


@pytest.mark.parametrize("text, found", [("fixed in c38fb5f, then", ["c38fb5f"]),
                                         ("(see 1755db9a)", ["1755db9a"]),
                                         ("weights_sha256=7f386226c9ef60b2", []),
                                         ("'x7.184642940994e+01'", []), ("a deadbeef cafe", []),
                                         ("frame 0000123 of", [])])
def test_the_hash_pattern_tells_a_commit_from_a_digest_and_a_number(text, found):
    assert HASH.findall(text) == found


def test_a_dated_heading_is_found():
    assert DATED_HEADING.findall("# Notes\n\n## 2026-11-26: the crop stage\n") != []
    assert DATED_HEADING.findall("## Results\nmeasured on 2026-11-26\n") == []
