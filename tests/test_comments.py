"""Comments and docstrings in src/ say why, not which issue asked (docs/style.md "To avoid"): no
"issue N" reference. pipeline/keys.py keeps its own until its frozen keys are rewritten from the
stages' declarations."""

from __future__ import annotations

import re
from pathlib import Path

import svolsdf

#: files whose issue references go with a rewrite under way
_LATER = {"pipeline/keys.py"}


def test_no_comment_names_an_issue():
    root = Path(svolsdf.__file__).parent
    found = [f"{p.relative_to(root)}:{i}: {line.strip()}"
             for p in sorted(root.rglob("*.py")) if str(p.relative_to(root)) not in _LATER
             for i, line in enumerate(p.read_text().splitlines(), 1)
             if re.search(r"\b[Ii]ssues? \d+", line)]
    assert not found, "\n".join(found)
