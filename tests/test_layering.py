"""Dependencies point down the package table (docs/architecture.md): the stages below fusion do not
import it, and the shared geometry helpers import only the scene."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "svolsdf"

def _imports(path: Path) -> set[str]:
    """Every module name ``path`` imports, at any depth (lazy imports count too)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            if node.module == "svolsdf":  # from svolsdf import pipeline
                names |= {f"svolsdf.{a.name}" for a in node.names}
    return names


def _modules(package: str):
    return sorted((SRC / package).rglob("*.py"))


@pytest.mark.parametrize("package", ["geometry", "mvs", "prior", "field", "render", "ibr"])
def test_stages_below_fusion_do_not_import_it(package):
    bad = [f"{p.relative_to(SRC)}: {m}" for p in _modules(package)
           for m in _imports(p) if m == "svolsdf.fusion" or m.startswith("svolsdf.fusion.")]
    assert not bad, "import svolsdf.geometry instead: " + "; ".join(bad)


def test_io_imports_nothing_above_it():
    # scene and every stage read and write files through io; the run folder's reader
    # (io/runfolder.py) leaves config.yaml to the config package's loader
    bad = [f"{p.relative_to(SRC)}: {m}" for p in _modules("io") for m in _imports(p)
           if m.startswith("svolsdf.") and not m.startswith(("svolsdf.io", "svolsdf.errors"))]
    assert not bad, "; ".join(bad)


def test_geometry_imports_only_the_scene():
    bad = [f"{p.relative_to(SRC)}: {m}" for p in _modules("geometry") for m in _imports(p)
           if m.startswith("svolsdf.") and not m.startswith(("svolsdf.scene", "svolsdf.geometry"))]
    assert not bad, "; ".join(bad)


@pytest.mark.parametrize("package", ["scene", "io", "geometry", "mvs", "prior", "field",
                                     "render", "ibr", "fusion", "optimize", "evaluate",
                                     "calibrate", "config"])
def test_components_do_not_import_the_pipeline_or_the_commands(package):
    # runs are opened (svolsdf.pipeline.Run) and driven only by commands/ and cli/
    bad = [f"{p.relative_to(SRC)}: {m}" for p in _modules(package) for m in _imports(p)
           if m.startswith(("svolsdf.pipeline", "svolsdf.commands", "svolsdf.cli"))]
    assert not bad, "; ".join(bad)


def test_the_registry_machinery_imports_only_the_errors():
    # svolsdf/registry.py sits beside errors.py, below every component whose registry uses it
    bad = [m for m in _imports(SRC / "registry.py")
           if m.startswith("svolsdf.") and m != "svolsdf.errors"]
    assert not bad, "; ".join(bad)
