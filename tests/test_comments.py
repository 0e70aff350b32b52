"""Comments and docstrings in src/ say why, not which issue asked (docs/style.md "To avoid"): no
"issue N" reference."""

from __future__ import annotations

import re
from pathlib import Path

import svolsdf


def test_no_comment_names_an_issue():
    root = Path(svolsdf.__file__).parent
    found = [f"{p.relative_to(root)}:{i}: {line.strip()}"
             for p in sorted(root.rglob("*.py"))
             for i, line in enumerate(p.read_text().splitlines(), 1)
             if re.search(r"\b[Ii]ssues? \d+", line)]
    assert not found, "\n".join(found)
