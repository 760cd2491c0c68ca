"""The README's figures table is read by people: every cell holds a figure or its conditions (seeds, scenario,
frames) in at most 200 characters, and no provenance (a commit hash, an issue number), which belongs in
docs/history.md; the full table in docs/usage.md keeps the same rule. The checker runs on text, so a test shows
it catching a planted cell. The README stays a ten-minute read: at most MAX_README_WORDS words."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"
USAGE = README.parent / "docs" / "usage.md"
HEADING = "## Figures that matter"
FULL_HEADING = "### The figures, in full"
MAX_README_WORDS = 2500
MAX_CELL = 200
HASH = re.compile(r"\b(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b")  # digits and letters, as git prints
ISSUE = re.compile(r"\bissues? #?\d+|#\d+\b", re.IGNORECASE)


def table_rows(text: str, heading: str = HEADING) -> list[list[str]]:
    """The cells of each body row of the first table under the heading (the header and its rule left out)."""
    section = text.split(heading + "\n", 1)[1].split("\n## ", 1)[0]
    lines = section.split("\n")
    first = next(i for i, line in enumerate(lines) if line.startswith("|"))
    rows = []
    for line in lines[first + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]])
    return rows


def bad_cells(rows: list[list[str]]) -> list[str]:
    """What is wrong with each cell that breaks the rule: its length, a commit hash, an issue number."""
    out = []
    for row in rows:
        for cell in row:
            head = f"{row[0][:30]!r}: {cell[:40]!r}..."
            if len(cell) > MAX_CELL:
                out.append(f"{head} {len(cell)} characters (at most {MAX_CELL})")
            for pattern, what in ((HASH, "a commit hash"), (ISSUE, "an issue number")):
                if m := pattern.search(cell):
                    out.append(f"{head} holds {what}, {m.group(0)!r}: provenance goes to docs/history.md")
    return out


def test_the_figures_table_has_short_cells_without_provenance():
    rows = table_rows(README.read_text(encoding="utf-8"))
    assert len(rows) >= 5 and all(len(r) == 3 for r in rows), "the table: what | figure | conditions"
    assert bad_cells(rows) == []


def test_the_full_table_in_the_usage_guide_keeps_the_rule():
    rows = table_rows(USAGE.read_text(encoding="utf-8"), FULL_HEADING)
    assert len(rows) >= 10 and all(len(r) == 3 for r in rows), "the table: what | figure | conditions"
    assert bad_cells(rows) == []


def test_the_readme_is_a_ten_minute_read():
    words = len(README.read_text(encoding="utf-8").split())
    assert words <= MAX_README_WORDS, f"README.md has {words} words (at most {MAX_README_WORDS}): move detail to docs/"


def test_the_checker_catches_a_planted_cell():
    text = ("# x\n\n" + HEADING + "\n\nintro\n\n| what | figure | conditions |\n|---|---|---|\n"
            "| speed | 9.2 us | 1000 runs, seed 0, 2026-11-27 |\n"
            "| tracking | NEES 9.0 | the tracker of c5751ae |\n"
            "| floors | met | every floor of issue 28 |\n"
            f"| long | {'x' * 201} | seeds 0-7 |\n\nafter\n\n## Next\n\n| a | b |\n|---|---|\n| {'y' * 300} | c |\n")
    rows = table_rows(text)
    assert [r[0] for r in rows] == ["speed", "tracking", "floors", "long"]
    found = bad_cells(rows)
    assert len(found) == 3 and "c5751ae" in found[0] and "issue 28" in found[1] and "201 characters" in found[2]
    assert bad_cells([["ukf", "1000000 runs, 6001 steps, facade", "seed 8181"]]) == []  # no hex letters, or no digit
