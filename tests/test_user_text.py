"""What a user reads says what the harness does, not how its work was organised.

The manual (``docs/``, the README), the package's strings and comments, and the benchmarks' text
never cite an internal issue number (nobody who clones the repository can open one), never point
at a commit as evidence, and never tell which session or machine loan found something. History
belongs in ``CHANGELOG.md``, in a user's words. A commit may still name *where* a bench figure was
measured ("measured on 2026-11-25 on ``8628b56``"): that is provenance, not evidence.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Phrases that cite internal work: an issue by number, "the issue's", a session or a loan.
BANNED = [
    (re.compile(r"\bissues?\s*#?\d+", re.I), "an internal issue number"),
    (re.compile(r"\bthe issue\b|\bissue's\b", re.I), "the issue a change came from"),
    (re.compile(r"\b(previous|earlier) session\b|\bsession's (machine|measurement)", re.I),
     "the work session that measured it"),
    (re.compile(r"\b(was|were) lent\b|\blent to\b|device machine", re.I),
     "how a machine was come by"),
    (re.compile(r"\bturned out\b|\bwas replaced\b", re.I), "narrated history"),
    (re.compile(r"\bearlier (?:version|default|code|release|behaviour)s?\b"
                r"|\bthe (?:earlier|previous|old) (?:default|one|rule|behaviour)\b"
                r"|\bdefaults? (?:of earlier|before)\b|\b(?:as|than|since) before\b"
                r"|\bbefore (?:the|these|this) (?:changes?|fix)\b"
                r"|\b(?:it|they|this|that) used to\b|\bused to be\b",
                re.I), "history told where the present belongs"),
]  # fmt: skip

#: A commit as evidence: a bare short hash in parentheses or after a comma (not "on `abc1234`").
COMMIT_AS_EVIDENCE = re.compile(r"(?:\(|, )([0-9a-f]{7,12})\)")


def user_files() -> list[Path]:
    """The manual, the README, the package's modules and the benchmarks' modules."""
    files = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    for pkg in ("harness", "bench", "examples"):
        files += sorted(p for p in (ROOT / pkg).rglob("*.py") if "__pycache__" not in p.parts)
    return files


def offences(text: str, where: str) -> list[str]:
    """Each line of ``text`` (the file ``where``) that cites internal work, with what it cites."""
    found = []
    for i, line in enumerate(text.splitlines(), 1):
        for pattern, what in BANNED:
            m = pattern.search(line)
            if m:
                found.append(f"{where}:{i}: {what} ({m.group(0)!r})")
        m = COMMIT_AS_EVIDENCE.search(line)
        if m and re.search(r"[a-f]", m.group(1)) and re.search(r"\d", m.group(1)):
            found.append(f"{where}:{i}: a commit as evidence ({m.group(1)!r})")
    return found


def test_no_internal_references_in_what_users_read() -> None:
    bad = [
        o
        for p in user_files()
        for o in offences(p.read_text(encoding="utf-8"), str(p.relative_to(ROOT)))
    ]
    assert not bad, "what users read cites internal work:\n" + "\n".join(bad)


@pytest.mark.parametrize(
    "line, caught",
    [
        ("the default since issue 63", True),
        ("Issues 50 and 62 measured", True),
        ("the issue's line 60 s", True),
        ("nothing, b63570e): R@1 0.2804", True),
        ("no device machine was lent in that session", True),
        ("found in the previous session", True),
        ("the GPU machine lent to one session", True),
        ("the default of earlier versions", True),
        ("keypoints on the colour regions (the earlier default)", True),
        ("the autoencoder, the default before", True),
        ("are cropped exactly as before", True),
        ("Before the change, the ranks differed", True),
        ("The same command took 153 s before these changes", True),
        ("the pairing it used to do", True),
        ("the objects of this session's frames", False),
        ("the earlier frame of the pair, and the frame before it", False),
        ("the model is used to rank the boxes", False),
        ("before any work: the config, then the flags", False),
        ("measured on 2026-11-25 on `8628b56`", False),
        ("the session's frames, one map session", False),
        ("R@1 0.25 (0.24, 0.26)", False),
    ],
)
def test_the_check_catches_what_it_names(line: str, caught: bool) -> None:
    """The patterns on lines written for the purpose: each kind of citation, and fair uses."""
    assert bool(offences(line, "probe.md")) is caught, offences(line, "probe.md")
