"""The front page and the docs point only at files that exist: every number they keep links to its report."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def local_links(page: Path) -> list[str]:
    targets = LINK.findall(page.read_text())
    return [t.split("#", 1)[0] for t in targets if not t.startswith(("http://", "https://", "mailto:", "#"))]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_linked_file_exists(page):
    links = local_links(page)
    missing = [t for t in links if not (page.parent / t).exists()]
    assert not missing, f"{page.name} links to missing files: {missing}"


def test_the_readme_links_every_docs_page():
    linked = {(ROOT / t).resolve() for t in local_links(ROOT / "README.md")}
    assert {p.resolve() for p in PAGES[1:]} <= linked


def test_committed_reports_name_no_machines_folders():
    pattern = re.compile(r"(/work/|/home/|/root/|/tmp/|/Users/)")
    found = []
    for path in sorted((ROOT / "benchmarks" / "results").rglob("*")):
        if path.is_file() and path.suffix in (".md", ".json", ".txt", ".csv"):
            found += [f"{path.relative_to(ROOT)}: {m.group(0)}" for m in pattern.finditer(path.read_text())]
    assert not found, found[:10]
