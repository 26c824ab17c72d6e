"""Docs describe the system as it is: size limits and no development-history narration.

History belongs in CHANGELOG.md (exempt). The phrase list targets the narration seen in this code
base ("in the fifth round", "this session", "issue 13's session", "round 3" as a work log); words
that are legitimate in the product (a teleop *session*, the second-pass *rounds* of `presim align`,
rounding) do not match: the patterns need an ordinal or a deictic word next to them.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC_MAX_LINES = 400
README_MAX_LINES = 200
README_MAX_BYTES = 12 * 1024

_ORDINAL = (r"(?:\d+(?:st|nd|rd|th)|first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|"
            r"eleventh|twelfth|\w+teenth|\w+tieth(?:-\w+)?|twenty-\w+)")
# Each pattern is matched case-insensitively against one line at a time.
NARRATION = [
    r"\bin the \w+ round\b",                      # "in the fifth round"
    r"\bthis round\b",
    r"\bthis session\b",
    r"\bround \d+\b(?! ?(?:px|pixels?|mm|cm|m|ms|s|%))",  # "round 3" (a work log), not "round 2 px"
    r"\bsession \d+\b",
    rf"\b{_ORDINAL} sessions?\b",                  # "the sixth session", "fourth and fifth sessions"
    r"\b(?:previous|earlier) (?:session|round)s?\b",  # not "the last round's Huber weights"
    r"\blast session\b",
    r"\bissue \d+'s session\b",
]
_NARRATION_RE = [re.compile(p, re.IGNORECASE) for p in NARRATION]

def _files() -> list[Path]:
    files = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]
    files += sorted((ROOT / "presim").rglob("*.py")) + sorted((ROOT / "benchmarks").glob("*.py"))
    return [f for f in files if f.is_file()]


def narration_hits(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line that narrates development history."""
    hits = []
    for n, line in enumerate(text.splitlines(), 1):
        if any(r.search(line) for r in _NARRATION_RE):
            hits.append((n, line.strip()))
    return hits


def test_narration_patterns_on_known_text():
    bad = ["measured in the fifth round", "this round's numbers", "done this session",
           "round 3 of the speed work", "session 4", "the sixth session added seeds",
           "(issue 13, twentieth session)", "as the previous session found", "issue 11's session",
           "the twenty-first session", "the 3rd session", "against the previous round",
           "fourth and fifth sessions"]
    good = ["the teleop session runs in a thread", "start_new_session=True",
            "values round to the nearest millimetre", "3 second-pass rounds", "--rematch-rounds 3",
            "halves round up, never to even", "a round base r = 0.25 m", "round 2 px off",
            "session.start()", "a second matching pass", "TeleopSession",
            "the last round's Huber weights", "3 rounds of the alternation"]
    assert all(narration_hits(t) for t in bad), [t for t in bad if not narration_hits(t)]
    assert not any(narration_hits(t) for t in good), [t for t in good if narration_hits(t)]


@pytest.mark.parametrize("path", sorted((ROOT / "docs").glob("*.md")), ids=lambda p: p.name)
def test_doc_size(path: Path):
    n = len(path.read_text(encoding="utf-8").splitlines())
    assert n <= DOC_MAX_LINES, f"{path.relative_to(ROOT)}: {n} lines > {DOC_MAX_LINES}"


def test_readme_size():
    readme = ROOT / "README.md"
    n = len(readme.read_text(encoding="utf-8").splitlines())
    size = readme.stat().st_size
    assert n <= README_MAX_LINES and size <= README_MAX_BYTES, \
        f"README.md: {n} lines (max {README_MAX_LINES}), {size} bytes (max {README_MAX_BYTES})"


def test_no_history_narration():
    report = []
    for f in _files():
        for n, line in narration_hits(f.read_text(encoding="utf-8")):
            report.append(f"{f.relative_to(ROOT)}:{n}: {line[:120]}")
    assert not report, ("development history belongs in CHANGELOG.md, not in docs or code:\n"
                        + "\n".join(report))
