"""The repository's docs are what code cites: every citation resolves, none points outside.

Code, tests and docs cite sections of ``docs/*.md`` by anchor (``docs/estimation.md#revolute-filter``);
a renamed heading would silently orphan them. Anchors are GitHub's heading slugs.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SOURCES = [*ROOT.glob("services/**/*.py"), *ROOT.glob("tests/**/*.py"), *ROOT.glob("bench/*.py"),
           *ROOT.glob("docker/**/*"), ROOT / "README.md", ROOT / "Makefile", ROOT / "pyproject.toml"]
DOC_PAGES = sorted(DOCS.glob("*.md"))

CODE_CITATION = re.compile(r"docs/([a-z_]+\.md)(?:#([a-z0-9_-]+))?")
DOC_LINK = re.compile(r"\]\(([a-z_]+\.md)(?:#([a-z0-9_-]+))?\)")
SAME_PAGE_LINK = re.compile(r"\]\(#([a-z0-9_-]+)\)")
# Upper-case Markdown file names other than README.md, and bracketed tags such as "[ABC]" with a
# section number: the marks of design documents that are not part of this repository.
FOREIGN_DOCUMENT = re.compile(r"\b(?!README\.md)[A-Z][A-Z0-9_]{2,}\.md\b|\[[A-Z]{3}\]\s*(?:§|\d)")


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading text."""
    text = heading.strip().lower().replace("`", "")
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """Every heading anchor of ``page`` (duplicates get GitHub's ``-1``, ``-2`` suffixes)."""
    seen: dict[str, int] = {}
    out: set[str] = set()
    in_code = False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            in_code = not in_code
            continue
        m = re.match(r"#{1,6} (.+)", line)
        if in_code or not m:
            continue
        base = slug(m.group(1))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def _citations() -> list[tuple[Path, str, str | None]]:
    found = []
    for path in SOURCES:
        if path.is_file():
            for page, anchor in CODE_CITATION.findall(path.read_text(errors="replace")):
                found.append((path, page, anchor or None))
    for path in DOC_PAGES:
        for page, anchor in DOC_LINK.findall(path.read_text()):
            found.append((path, page, anchor or None))
        for anchor in SAME_PAGE_LINK.findall(path.read_text()):
            found.append((path, path.name, anchor))
    return found


def test_slug_follows_github() -> None:
    assert slug("Hand-body EKF") == "hand-body-ekf"
    assert slug("Departures from the paper and OMIP") == "departures-from-the-paper-and-omip"
    assert slug("`handkse` command (v1)") == "handkse-command-v1"


def test_every_cited_doc_section_exists() -> None:
    citations = _citations()
    assert len(citations) > 30  # the code does cite the docs
    table = {page.name: anchors(page) for page in DOC_PAGES}
    broken = [f"{path.relative_to(ROOT)}: docs/{page}" + (f"#{anchor}" if anchor else "")
              for path, page, anchor in citations
              if page not in table or (anchor is not None and anchor not in table[page])]
    assert not broken, "citations of missing docs or headings:\n" + "\n".join(broken)


def test_nothing_cites_documents_outside_the_repository() -> None:
    offenders = []
    for path in [*SOURCES, *DOC_PAGES]:
        if path.is_file():
            for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                if FOREIGN_DOCUMENT.search(line) and path != Path(__file__).resolve():
                    offenders.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not offenders, "move what these cite into docs/:\n" + "\n".join(offenders)
