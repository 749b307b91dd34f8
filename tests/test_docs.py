"""README.md is the user's entry point: at most 10 KB, linking every document; the documents' links
resolve; the documents, the code and the tests describe the product as it is (git keeps its history)."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
HISTORY = re.compile(
    r"\b(previously|used to|since version|no longer|version history|in earlier versions|formerly|"
    r"was changed|has been changed|this stop|last stop)\b",
    re.IGNORECASE,
)


def docs() -> list[Path]:
    return sorted((ROOT / "docs").glob("*.md"))


def test_readme_is_at_most_10_kb_and_links_every_document():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.encode("utf-8")) <= 10 * 1024
    linked = {(ROOT / target).resolve() for target in LINK.findall(readme)}
    missing = [d.name for d in docs() if d.resolve() not in linked]
    assert not missing, f"README.md does not link {missing}"


def test_relative_links_resolve():
    broken = []
    for page in [ROOT / "README.md", *docs()]:
        for target in LINK.findall(page.read_text(encoding="utf-8")):
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (page.parent / target).exists():
                broken.append(f"{page.relative_to(ROOT)} -> {target}")
    assert not broken, broken


def test_documents_hold_no_history_of_earlier_versions():
    found = []
    for page in [ROOT / "README.md", *docs()]:
        for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
            m = HISTORY.search(line)
            if m:
                found.append(f"{page.relative_to(ROOT)}:{n}: {m.group(0)}")
    assert not found, found


# In code and tests: issue tags, comparisons with an earlier main and figures "it was": the commit
# messages and closing notes keep those, the code says what it does now.
CODE_HISTORY = re.compile(
    r"\b(issue \d+|issues? #\d+|on main|this stop|last stop|in earlier versions|formerly)\b"
    r"|\bwas \d+(\.\d+)? ?(%|mm|ms|px)",
    re.IGNORECASE,
)


def test_code_and_tests_hold_no_history_of_earlier_versions():
    found = []
    for tree in ("atlas_onboard", "tests"):
        for path in sorted((ROOT / tree).rglob("*.py")):
            if path == Path(__file__).resolve():
                continue
            for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                m = CODE_HISTORY.search(line)
                if m:
                    found.append(f"{path.relative_to(ROOT)}:{n}: {m.group(0)}")
    assert not found, found
