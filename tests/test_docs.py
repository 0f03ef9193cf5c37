"""The docs stay rooms a reader can find their way in.

docs/trainer.md and docs/runtime.md lead with what a user does and why; the dated figures live
in docs/measurements/ and the designs tried and dropped in docs/design-history.md. These checks
keep the two pages short, every ``fbgforce train`` option documented somewhere under docs/, and
every link and quoted section reference between the pages pointing at something that exists.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from fbgforce.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
#: Pages that must stay short enough to read: what a user does first, the figures elsewhere.
SHORT_PAGES = ("trainer.md", "runtime.md")
MAX_LINES = 500


def _pages() -> list[Path]:
    return sorted(DOCS.rglob("*.md")) + [ROOT / "README.md"]


def _subcommand(name: str):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return sub.choices[name]


def _slug(title: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces to hyphens."""
    title = re.sub(r"[`*_]", "", title.strip().lower())
    return re.sub(r"[^\w\- ]", "", title, flags=re.UNICODE).replace(" ", "-")


def _titles(page: Path) -> set[str]:
    """Headings and the bold or italic leads of paragraphs and bullets: what a quoted section
    reference such as ``docs/runtime.md, "In use"`` may name."""
    found: set[str] = set()
    for line in page.read_text().splitlines():
        heading = re.match(r"#+\s+(.*)", line)
        if heading:
            found.add(heading.group(1).strip())
        for m in re.finditer(r"(?:^|\s)\*\*([^*]+?)\*\*|(?:^|\s)\*([A-Z][^*]+?)\*", line):
            found.add((m.group(1) or m.group(2)).strip())
    return found


@pytest.mark.parametrize("name", SHORT_PAGES)
def test_short_pages_stay_short(name):
    lines = len((DOCS / name).read_text().splitlines())
    assert lines < MAX_LINES, (
        f"docs/{name} has {lines} lines (limit {MAX_LINES}): move dated figures to "
        f"docs/measurements/{name} and tried designs to docs/design-history.md")


def test_every_train_option_is_documented():
    text = "\n".join(p.read_text() for p in DOCS.rglob("*.md"))
    options = [o for a in _subcommand("train")._actions for o in a.option_strings
               if o.startswith("--") and o != "--help"]
    assert len(options) > 10
    missing = [o for o in options if not re.search(re.escape(o) + r"(?![\w-])", text)]
    assert not missing, f"fbgforce train options documented nowhere under docs/: {missing}"


def test_links_between_pages_resolve():
    broken = []
    for page in _pages():
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if re.match(r"[a-z]+:", target):
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            if not dest.exists():
                broken.append(f"{page.relative_to(ROOT)}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in {
                    _slug(t) for t in _titles(dest)}:
                broken.append(f"{page.relative_to(ROOT)}: {target} (no such heading)")
    assert not broken, "\n".join(broken)


def test_quoted_sections_of_the_trainer_and_runtime_pages_exist():
    ref = re.compile(r"((?:measurements/)?(?:trainer|runtime)\.md)\"?(?:'s)?,?\s+\(?\"([^\"]+)\"")
    titles = {}
    broken = []
    for page in _pages():
        text = re.sub(r"\s*\n\s*", " ", page.read_text())
        for m in ref.finditer(text):
            target, title = DOCS / m.group(1), m.group(2)
            if target not in titles:
                titles[target] = _titles(target)
            if not any(t.startswith(title) or (title.startswith(t) and len(t) > 3)
                       for t in titles[target]):
                broken.append(f"{page.relative_to(ROOT)}: {m.group(1)}, \"{title}\"")
    assert not broken, "sections quoted but not found:\n" + "\n".join(broken)
