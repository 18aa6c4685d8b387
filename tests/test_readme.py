"""The README stays short and its links stay working: every relative link in README.md and
docs/*.md names a file that exists, and the README's library example is the one
``tests/test_public_api.py`` runs (the ``calibration`` package docstring's)."""

from __future__ import annotations

import re
from pathlib import Path

import calibration
from tests.test_public_api import docstring_example

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def relative_links(page: Path) -> list[str]:
    return [t for t in LINK.findall(page.read_text(encoding="utf-8")) if "://" not in t]


def test_the_readme_is_short():
    assert len((ROOT / "README.md").read_text(encoding="utf-8").splitlines()) < 120


def test_every_relative_link_of_the_readme_and_docs_resolves():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    broken = [
        f"{page.relative_to(ROOT)}: {target}"
        for page in pages
        for target in relative_links(page)
        if not (page.parent / target).exists()
    ]
    assert relative_links(ROOT / "README.md"), "the README links to its docs"
    assert broken == []


def _code(text: str) -> list[str]:
    return [line.split("#")[0].rstrip() for line in text.splitlines() if line.strip()]


def test_the_readme_library_example_is_the_one_the_tests_run():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    block = re.search(r"```python\n(.*?)```", readme, re.S)
    assert block is not None
    assert _code(block.group(1)) == _code(docstring_example(calibration))
