"""Every runtime dependency of pyproject.toml is one the package imports (a dependency nothing
imports only costs users an install; the tests' own belong in the dev extra)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: distribution name -> the module it installs, where they differ
MODULE = {"scikit-image": "skimage", "pillow": "PIL", "pyyaml": "yaml"}


def _dependencies() -> list[str]:
    text = (REPO / "pyproject.toml").read_text()
    block = re.search(r"^dependencies = \[(.*?)^\]", text, re.M | re.S).group(1)
    return re.findall(r'^\s*"([A-Za-z0-9_.-]+)', block, re.M)


def _imported() -> set[str]:
    names = set()
    for p in (REPO / "src").rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names.add(node.module.split(".")[0])
    return names


def test_every_runtime_dependency_is_imported_by_the_package():
    deps = _dependencies()
    assert "torch" in deps and "pycolmap" in deps  # the list was read
    unused = [d for d in deps if MODULE.get(d.lower(), d.replace("-", "_")) not in _imported()]
    assert not unused, f"dependencies that src/ never imports: {unused} (drop them or move " \
                       "them to an extra)"
