"""Every measured number in README.md and docs/*.md is traced to a results file (issue 50).

The convention (docs/style.md, "Also kept": results are rendered from their data, and the docs
cite them):

- A *unit* is a paragraph, a list item (with its continuation lines) or a table row. Headings,
  code blocks and HTML comments are not units.
- A unit's *sources* are the results files it cites: a path `benchmarks/results/NAME.md` or
  `.json` (a `*` matches several), or a bare `NAME.md` that exists in benchmarks/results/ or
  benchmarks/results/history/. A table row and a list item also have the sources of their
  caption: the paragraph directly above the table or list (and a nested item its parent's).
  A design document (docs/method.md, ...) is not a source: cite the results file.
- Every number of a unit that cites a source must occur in one of its sources. Numbers compare
  as decimals with the sign and thousands separators dropped: 0.70 matches 0.7 and -0.70, 1,024
  matches 1024; a number with k decimals also matches a source number with more decimals that
  rounds to it (1.23 matches 1.2304, 49 matches 48.9; 1.97 matches 1.975, which stands for a
  value in [1.9745, 1.9755]). A range (0.39-0.61, -3.5 to +16.6) is its two ends.
- A unit with a number but no source fails, unless the number is exempt by the rules below or
  its file is a design document (DESIGN_DOCS, each with the reason).
- A unit (or its caption) that says "not reproducible" states numbers whose runs are gone: they
  are kept as history and not checked.

Numbers that are not measurements are exempt by these rules (EXEMPT), nothing else:

1. inside `code` (options and their values, commands, file names, constants of the code);
2. inside a link target, a path (a word with a "/" and a letter: ../shared/data) or a file
   name (x.md, x.png);
3. part of a name: letters before the digits (s411, synth301-305, dtu65, x2), a size WxH
   (768x576, 8x256), a date (2026-12-03), a commit (a run of 7 or more hex digits), a version
   (3.10 after "Python", a.b.c), a section of a design document (docs/method.md 4.2, habit 5),
   a power (a grid of 128^3) or a list marker;
4. the integers right after a naming word (seed, seeds, scan, scans, issue, issues, commit,
   commits, view, views, stage, stages, section, sections, habit, Table, Eq., DTU, and a venue
   before its year: ICCV 2023) and the integers listed with them ("views 25, 22, 28", "seeds 501
   and 502", "stages 2-3", "DTU 65"), unless a unit follows them ("views 385 s" is a
   measurement);
5. a threshold, target or setting: the numbers right after a comparison or an equals sign
   (<, >, <=, >=, =) and the numbers listed with them ("k = 4, 6, 8", "Chamfer <= 1.15").

README's "What to expect" table is checked like any other unit: its rows cite
benchmarks/results/table1.md through their caption.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
HISTORY = RESULTS / "history"

# Documents that describe the code and the paper, not measurements: their units without a
# results file are constants of the method or the code, the paper's figures and equation
# numbers. A unit of theirs that cites a results file is checked like any other.
DESIGN_DOCS = {
    "docs/method.md": "the method as the paper and the released code define it: its numbers "
                      "are the paper's constants, figures and equation numbers",
    "docs/architecture.md": "the code's layout: numbers are option values and line counts",
    "docs/style.md": "habits of the code: habit numbers and limits",
    "docs/run-folder.md": "the run folder's files: option values and formats",
    "docs/dependencies.md": "version bounds of the dependencies",
    "docs/benchmark-on-ray.md": "how to run the benchmark on a cluster: commands and sizes",
}

NUMBER = re.compile(r"\d+(?:,\d{3})+(?:\.\d+)?|\d+(?:\.\d+)?")
UNIT_AFTER = re.compile(r"\s*(?:%|s\b|min\b|minutes\b|mm\b|GB\b|MB\b|dB\b|x\b|px\b)")
NAMING = re.compile(
    r"(?<![\w.])(?i:seeds?|scans?|issues?|commits?|views?|stages?|sections?|habit|table|eq\.|dtu"
    r"|iccv|cvpr|eccv)"
    r"(?P<list>(?:\s*(?:,|/|and|or|-|\s)\s*\d+(?![\d.,]\d))+)")
EXEMPT = [
    re.compile(r"`[^`]*`"),                                       # 1 code
    re.compile(r"(?:docs/)?method\.md(?:'s)?\s+\d+(?:\.\d+)*(?:\s*(?:,|and|-)\s*\d+(?:\.\d+)*)*"),
    re.compile(r"\]\([^)]*\)"),                                   # 2 link targets
    re.compile(r"\S*[A-Za-z_~]\S*/\S*|\S*/\S*[A-Za-z_]\S*"),           # 2 paths
    re.compile(r"[\w.*-]+\.(?:md|json|png|jpg|py|ply|npy|npz|yaml|txt)\b"),  # 2 file names
    re.compile(r"habit\s+\d+"),
    re.compile(r"\d{4}-\d{2}-\d{2}"),                             # 3 dates
    re.compile(r"\b\d+(?:\.\d+)?x\d+(?:x\d+)?\b"),                # 3 sizes
    re.compile(r"\b[0-9a-f]{7,40}\b"),                            # 3 commits
    re.compile(r"\b\d+\.\d+\.\d+\b"),                             # 3 versions a.b.c
    re.compile(r"(?:Python|torch|CUDA)\D{0,4}\d+(?:\.\d+)*"),     # 3 versions
    re.compile(r"[A-Za-z_]+\d+(?:[-\d.]*\d)?"),                   # 3 names (s411, synth301-305)
    re.compile(r"\d+[A-Za-z_]*[A-WYZa-wyz_]\w*"),                 # 3 names (3D, 2nd), not 1.5x
    re.compile(r"\d*\^\s*-?\d+"),                                 # 3 powers (128^3)
    re.compile(r"(?:<=|>=|[<>=\u2264\u2265])\s*[-+]?\d+(?:\.\d+)?"       # 5 thresholds
               r"(?:\s*(?:,|/|and|or)\s*[-+]?\d+(?:\.\d+)?)*"),
    re.compile(r"^\s*(?:\d+\.|[-*])\s"),                          # 3 list markers
]


@dataclass
class Unit:
    file: str
    line: int
    text: str
    caption: Unit | None = None
    sources: list[Path] = field(default_factory=list)
    table_row: bool = False

    def all_sources(self) -> list[Path]:
        out, u = [], self
        while u is not None:
            out += [s for s in u.sources if s not in out]
            u = u.caption
        return out

    def says_not_reproducible(self) -> bool:
        u = self
        while u is not None:
            if "not reproducible" in " ".join(u.text.lower().split()):
                return True
            u = u.caption
        return False

    def cites(self, name: str) -> bool:
        u = self
        while u is not None:
            if name in u.text:
                return True
            u = u.caption
        return False


# -------------------------------------------------------------------------------------------------
# Markdown into units

LIST_ITEM = re.compile(r"^(?P<indent>\s*)(?:[-*]|\d+\.)\s+")


def units_of(name: str, text: str, roots: tuple[Path, ...] = ()) -> list[Unit]:
    """The units of one Markdown file, each with its caption (see the module docstring)."""
    lines = text.split("\n")
    out: list[Unit] = []
    in_code = False
    last_para: Unit | None = None      # the paragraph a following table or list hangs on
    items: list[tuple[int, Unit]] = []  # open list items (indent, unit), outermost first
    cur: Unit | None = None             # the paragraph or item being read
    blank_before = True
    in_table = False
    for i, raw in enumerate(lines, 1):
        line = raw.rstrip()
        if line.lstrip().startswith("```"):
            in_code = not in_code
            cur = None
            continue
        if in_code or line.lstrip().startswith("<!--"):
            continue
        if not line.strip():
            cur = None
            blank_before = True
            if in_table:
                in_table = False
                last_para = None
            continue
        if line.startswith("#"):
            cur, last_para, items, in_table = None, None, [], False
            blank_before = False
            continue
        if line.lstrip().startswith("|"):
            if not in_table:
                in_table = True
                caption = last_para
            if not re.fullmatch(r"\s*\|[\s|:-]*", line):
                out.append(Unit(name, i, line, caption=caption, table_row=True))
            cur = None
            blank_before = False
            continue
        m = LIST_ITEM.match(line)
        if m:
            indent = len(m["indent"])
            while items and items[-1][0] >= indent:
                items.pop()
            parent = items[-1][1] if items else last_para
            cur = Unit(name, i, line, caption=parent)
            items.append((indent, cur))
            out.append(cur)
        elif cur is not None:
            cur.text += "\n" + line
        else:
            if blank_before and not line.startswith(" "):
                items = []
            cur = Unit(name, i, line.lstrip("> "))
            out.append(cur)
            if not items:
                last_para = cur
            else:  # a paragraph inside a list item continues it
                cur.caption = items[-1][1]
        blank_before = False
    for u in out:
        u.sources = sources_of(u.text, roots or (RESULTS, HISTORY))
    return out


CITE = re.compile(r"(?:benchmarks/results/|(?<![\w/.-]))"
                  r"(?P<name>[\w*-]+(?:/[\w*-]+)*\.(?:md|json))")


def sources_of(text: str, roots: tuple[Path, ...] = ()) -> list[Path]:
    """The results files ``text`` cites (existing files only)."""
    out: list[Path] = []
    for m in CITE.finditer(text.replace("\n", " ")):
        name = m["name"]
        full = m.group().startswith("benchmarks/results/")
        for root in roots or (RESULTS, HISTORY):
            found = sorted(root.glob(name))
            if not full:
                found = [p for p in found if p.parent == root]
            out += [p for p in found if p.is_file() and p not in out]
    return out


# -------------------------------------------------------------------------------------------------
# numbers


def measured_numbers(text: str) -> list[str]:
    """The numbers of ``text`` that no rule exempts (module docstring), as written."""
    t = text
    for rx in EXEMPT:
        t = rx.sub(lambda m: " " * len(m.group()), t)
    # a naming word's integers, unless a unit follows them (a measurement)
    out = []
    named = set()
    for m in NAMING.finditer(t):
        if not UNIT_AFTER.match(t, m.end()):
            named.update(range(m.start("list"), m.end("list")))
    for m in NUMBER.finditer(t):
        if m.start() in named:
            continue
        out.append(m.group())
    return out


def _dec(s: str) -> Decimal | None:
    try:
        return Decimal(s.replace(",", ""))
    except InvalidOperation:
        return None


def _decimals(s: str) -> int:
    return len(s.split(".")[1]) if "." in s else 0


def numbers_in(path: Path, cache: dict = {}) -> dict[int, set[Decimal]]:  # noqa: B006
    """{decimals: {values}} of every number written in ``path``."""
    if path not in cache:
        by: dict[int, set[Decimal]] = {}
        for m in NUMBER.finditer(path.read_text(errors="replace")):
            d = _dec(m.group())
            if d is not None:
                by.setdefault(_decimals(m.group().replace(",", "")), set()).add(d)
        cache[path] = by
    return cache[path]


def occurs(number: str, sources: list[Path]) -> bool:
    """Whether ``number`` occurs in one of ``sources``, equal or rounded (module docstring)."""
    d, k = _dec(number), _decimals(number.replace(",", ""))
    if d is None:
        return False
    for src in sources:
        by = numbers_in(src)
        if any(d == v for vals in by.values() for v in vals):
            return True
        # the source's number is itself rounded to m decimals: the value it stands for lies
        # within half its last place, and the doc's number rounds that value to k decimals
        if any(abs(v - d) <= (Decimal(5).scaleb(-k - 1) + Decimal(5).scaleb(-m - 1))
               for m, vals in by.items() if m > k for v in vals):
            return True
    return False


# -------------------------------------------------------------------------------------------------
# the check


def _shown(p: Path) -> str:
    return p.relative_to(REPO).as_posix() if p.is_relative_to(REPO) else p.name


def claim_problems(name: str, text: str, roots: tuple[Path, ...] = ()) -> list[str]:
    """Every number of ``text`` (the file ``name``, relative to the repository) that breaks the
    convention, as "file:line: why"."""
    out = []
    for u in units_of(name, text, roots):
        nums = measured_numbers(u.text)
        if not nums or u.says_not_reproducible():
            continue
        srcs = u.all_sources()
        if not srcs:
            if name not in DESIGN_DOCS:
                out.append(f"{name}:{u.line}: {', '.join(nums)} with no results file cited "
                           f"({u.text.strip()[:70]!r})")
            continue
        missing = [n for n in nums if not occurs(n, srcs)]
        if missing:
            out.append(f"{name}:{u.line}: {', '.join(missing)} not in "
                       f"{', '.join(_shown(p) for p in srcs)} "
                       f"({u.text.strip()[:70]!r})")
    return out


def checked_files() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def test_every_measured_number_is_traced_to_a_results_file():
    bad = []
    for p in checked_files():
        bad += claim_problems(p.relative_to(REPO).as_posix(), p.read_text())
    assert not bad, f"{len(bad)} problem(s):\n" + "\n".join(bad)


def test_design_documents_exist():
    for name in DESIGN_DOCS:
        assert (REPO / name).is_file(), name


# -------------------------------------------------------------------------------------------------
# the check itself


SXS = "benchmarks/results/sxs.md"
# a results file of the tests' own, standing in for benchmarks/results/sxs.md
SXS_TEXT = """| scene | new/old | points change |
|---|---:|---:|
| a | 0.78 | -2.2 % |
| b | 0.9103 | +1.7 % |
- mean 0.82; nine views: wall 666 s
"""


@pytest.fixture
def results_root(tmp_path) -> Path:
    (tmp_path / "sxs.md").write_text(SXS_TEXT)
    return tmp_path


def _problems(text: str, root: Path, name: str = "docs/x.md") -> list[str]:
    return claim_problems(name, text, roots=(root,))


@pytest.mark.parametrize("text", [
    f"Wall new/old 0.78-0.91 (mean 0.82) ({SXS}).",
    f"Wall new/old 0.780-0.910, mean 0.8 ({SXS}).",           # trailing zeros, rounding
    f"Points Chamfer -2.2 to +1.7 % ({SXS}).",                # a signed range
    "Nine views take 666 s (sxs.md).",                        # a bare name of a results file
    "Seeds 501 and 502, DTU 65, views 25, 22, 28, commit 4ce07e5 on 2026-12-03 at 768x576.",
    "Use `--set mesh.support=4` (docs/method.md 8.3, habit 5) with Python 3.10.",
    "Scenes s411, synth301-305 and dtu65; 128^3 voxels; stages 2-3; k = 4, 6, 8; <= 1.15.",
    f"Caption ({SXS}):\n\n| a | b |\n|---|---|\n| 0.78 | 0.91 |",
    f"Caption ({SXS}):\n\n- 0.78\n  - 0.91",
    "A table kept as history, not\nreproducible:\n\n| 1.024 | 1.042 |",
])
def test_the_convention_accepts(text, results_root):
    assert _problems(text, results_root) == []


@pytest.mark.parametrize("text, expected", [
    (f"Wall new/old 0.78-0.93 ({SXS}).", "0.93 not in"),     # a misstated range end
    (f"Three of six scenes reach 0.45: 0.78-0.91 ({SXS}).", "0.45 not in"),
    ("Points Chamfer 1.91 -> 1.79 mm.", "no results file cited"),
    (f"Nine views 385 s ({SXS}).", "385 not in"),             # "views N s" is a measurement
    ("Caption without a file:\n\n| 0.78 | 0.91 |", "no results file cited"),
    ("The mesh is 1.16 times the points (docs/meshing.md).", "no results file cited"),
    (f"Points Chamfer 1.16 ({SXS}, not a results file: benchmarks/results/none.md).",
     "1.16 not in"),
])
def test_the_convention_rejects(text, expected, results_root):
    msgs = _problems(text, results_root)
    assert any(expected in m for m in msgs), msgs


def test_a_design_document_may_state_constants_but_its_citations_are_checked(results_root):
    assert _problems("The paper trains 100 000 steps at lr 5e-4.", results_root,
                     "docs/method.md") == []
    msgs = _problems(f"Measured: 0.93 ({SXS}).", results_root, "docs/method.md")
    assert any("0.93 not in" in m for m in msgs), msgs


def test_readme_table1_rows_are_checked_against_table1(results_root):
    text = ("Means (benchmarks/results/table1.md):\n\n| method | Chamfer |\n|---|---|\n"
            "| S-VolSDF | 9.99 |")
    assert _problems(text, results_root, "README.md") != []
    assert _problems(text, results_root) != []
