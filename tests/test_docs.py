"""The repository carries its own design: every citation of docs/method.md, docs/architecture.md
and docs/style.md in src/, tests/ and benchmarks/ resolves inside the repository (the file
exists; a method section number is a heading of docs/method.md; a quoted architecture section is
a heading of docs/architecture.md; a style habit number is a habit of docs/style.md), and nothing
cites the design documents by a bare name or a path outside the repository."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
SCANNED = ("src", "tests", "benchmarks")
SUFFIXES = {".py", ".md", ".txt", ".toml", ".yaml", ".yml"}

# "docs/method.md 4.2", "docs/method.md's 6.1", "(docs/method.md\n    # 1.4: ...)",
# "docs/method.md 1.1-1.3"; text without a number ("docs/method.md's constants") cites the file
_NUM = r"\d+(?:\.\d+)*"
METHOD_CITE = re.compile(r"docs/method\.md(?:'s)?[\s#]*(?:sections?\s+)?"
                         rf"(?P<a>{_NUM})(?:\s*-\s*(?P<b>{_NUM}))?")
ARCH_CITE = re.compile(r"docs/architecture\.md,?[\s#]*\"(?P<name>[^\"\n]+)\"")
STYLE_CITE = re.compile(r"docs/style\.md,?[\s#]*habit\s+(?P<n>\d+)")
ANY_CITE = re.compile(r"docs/(?P<doc>method|architecture|style)\.md")
# built from pieces so that this file does not match itself
_BARE_NAMES = "|".join(n.upper() for n in ("method", "architecture", "style"))
BARE_CITE = re.compile(rf"(?<![\w/.-])(?:{_BARE_NAMES})\.md")
OUTSIDE = re.compile("shared" + "/" + "design")
HEADING = re.compile(rf"^#{{1,6}}\s+(?P<num>{_NUM})\.?\s", re.M)
ANY_HEADING = re.compile(r"^#{1,6}\s+(?P<text>.+)$", re.M)
HABIT = re.compile(r"^\s*(?P<n>\d+)\.\s", re.M)


def _scanned_files() -> list[Path]:
    files = []
    for top in SCANNED:
        for p in sorted((REPO / top).rglob("*")):
            if p.is_file() and p.suffix in SUFFIXES and "__pycache__" not in p.parts:
                files.append(p)
    return files


def _docs() -> dict[str, str]:
    """{name: text} of the three design documents ("" when missing)."""
    return {d: (DOCS / f"{d}.md").read_text() if (DOCS / f"{d}.md").is_file() else ""
            for d in ("method", "architecture", "style")}


def problems(name: str, text: str, docs: dict[str, str]) -> list[str]:
    """Every citation in ``text`` (from file ``name``) that does not resolve in ``docs``."""
    out = []
    method_sections = {m["num"] for m in HEADING.finditer(docs["method"])}
    arch_headings = [m["text"].lower() for m in ANY_HEADING.finditer(docs["architecture"])]
    habits = {m["n"] for m in HABIT.finditer(docs["style"])}

    def line(pos: int) -> int:
        return text.count("\n", 0, pos) + 1

    for m in ANY_CITE.finditer(text):
        if not docs[m["doc"]]:
            out.append(f"{name}:{line(m.start())}: docs/{m['doc']}.md does not exist")
    for m in METHOD_CITE.finditer(text):
        for num in filter(None, (m["a"], m["b"])):
            if num not in method_sections:
                out.append(f"{name}:{line(m.start())}: docs/method.md has no section {num}")
    for m in ARCH_CITE.finditer(text):
        if not any(m["name"].lower() in h for h in arch_headings):
            out.append(f"{name}:{line(m.start())}: docs/architecture.md has no section "
                       f"{m['name']!r}")
    for m in STYLE_CITE.finditer(text):
        if m["n"] not in habits:
            out.append(f"{name}:{line(m.start())}: docs/style.md has no habit {m['n']}")
    for m in BARE_CITE.finditer(text):
        out.append(f"{name}:{line(m.start())}: bare {m.group()} (cite docs/<name>.md)")
    for m in OUTSIDE.finditer(text):
        out.append(f"{name}:{line(m.start())}: points outside the repository ({m.group()})")
    return out


def test_design_documents_exist_and_number_their_sections():
    docs = _docs()
    assert all(docs.values()), "docs/method.md, docs/architecture.md and docs/style.md must exist"
    sections = {m["num"] for m in HEADING.finditer(docs["method"])}
    # the top-level sections 0-9 of the method, and the paper-vs-code items that code cites
    assert {str(i) for i in range(10)} <= sections
    assert {f"9.2.{i}" for i in range(1, 15)} <= sections


def test_every_citation_resolves_in_the_repository():
    docs = _docs()
    files = _scanned_files()
    assert len(files) > 50
    found = sum(len(ANY_CITE.findall(p.read_text(errors="replace"))) for p in files)
    assert found > 100, "the citations were not found: has the citation form changed?"
    bad = [msg for p in files
           for msg in problems(p.relative_to(REPO).as_posix(), p.read_text(errors="replace"),
                               docs)]
    assert not bad, "\n".join(bad[:30])


def test_docs_and_readme_do_not_depend_on_files_outside_the_repository():
    docs = _docs()
    files = sorted(DOCS.glob("*.md")) + [REPO / "README.md"]
    bad = [msg for p in files if p.is_file()
           for msg in problems(p.relative_to(REPO).as_posix(), p.read_text(), docs)]
    assert not bad, "\n".join(bad[:30])


_M = "docs/" + "method.md"
_A = "docs/" + "architecture.md"
_S = "docs/" + "style.md"


@pytest.mark.parametrize("text, expected", [
    (f"# the GCE loss ({_M} 4.2)", None),
    (f"the guide ({_M}\n    # 6.1: weight < 0.2)", None),
    (f"formats ({_M} 1.1-1.3)", None),
    (f"{_M}'s constants", None),
    (f'({_A} "Conventions")', None),
    (f"kept for the tests ({_S} habit 5)", None),
    (f"the loss ({_M} 4.9)", "no section 4.9"),
    (f"formats ({_M} 1.1-1.7)", "no section 1.7"),
    (f"a quirk ({_M}\n    9.2.15)", "no section 9.2.15"),
    (f'({_A} "Hallways")', "no section 'Hallways'"),
    (f"({_S} habit 42)", "no habit 42"),
    ("the loss (" + "METHOD" + ".md 4.2)", "bare " + "METHOD" + ".md"),
    ("see ../shared" + "/design/" + "ARCHITECTURE" + ".md", "outside the repository"),
    ("docs/" + "nothing.md 4.2 and docs/method.mdx", None),
])
def test_the_check_finds_wrong_citations(text, expected):
    msgs = problems("x.py", text, _docs())
    if expected is None:
        assert msgs == []
    else:
        assert any(expected in m for m in msgs), msgs


def test_a_missing_document_is_reported(tmp_path):
    docs = {**_docs(), "style": ""}
    msgs = problems("x.py", f"({_S} habit 5)", docs)
    assert any("docs/style.md does not exist" in m for m in msgs), msgs


def test_one_conftest_under_tests():
    """Tests import `shared_path` from the top-level conftest by name; a second conftest.py below
    tests/ would be imported under the same name first and break that import in a full run."""
    tests = Path(__file__).resolve().parent
    assert [p.relative_to(tests).as_posix() for p in tests.rglob("conftest.py")] == ["conftest.py"]


def test_the_readme_stays_short():
    """The README is for users (what, install, run, commands, what to expect): under 1,000
    words; results and their history belong in benchmarks/results/ and docs/ (issue 47)."""
    words = len((REPO / "README.md").read_text().split())
    assert words < 1000, f"README.md has {words} words; move detail to docs/ or benchmarks/"
