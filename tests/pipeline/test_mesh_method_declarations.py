"""What a mesh method declares (`svolsdf.fusion.mesh_methods.MeshMethod`): the options it reads
(``reads(cfg)``), whether its surface is the field's and whether it can be closed. The
config's validation and the pipeline's rules ask the declaration, never the name: a method
registered here, in the test file alone, is treated as its declaration says, and
`svolsdf.config.validate` and `svolsdf.pipeline.options` hold no built-in name."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import svolsdf
from svolsdf.config import preset, validate_config
from svolsdf.errors import InputError
from svolsdf.field.kinds import registered_field_kinds
from svolsdf.fusion.mesh_methods import (
    MeshInputs,
    get_mesh_method,
    register_mesh_method,
    registered_mesh_methods,
)
from svolsdf.pipeline import options


@register_mesh_method("test-closed-field", needs_field=True, closed=True,
                      options=("mesh.resolution",))
def _closed(m: MeshInputs):
    return m.field_mesh()


@register_mesh_method("test-open-field", needs_field=True)
def _open(m: MeshInputs):
    return m.field_mesh()


def test_the_builtin_methods_declare_the_options_they_read():
    cfg = preset("fast")
    cfg.mesh.poisson.depth, cfg.mesh.tsdf.fill_holes = 7, 0.0
    assert get_mesh_method("field").reads(cfg) == {}
    assert get_mesh_method("poisson").reads(cfg) == {"mesh.poisson.depth": 7,
                                                     "mesh.poisson.trim": cfg.mesh.poisson.trim}
    assert list(get_mesh_method("tsdf").reads(cfg)) == [
        "mesh.tsdf.resolution", "mesh.tsdf.truncation_steps", "mesh.tsdf.fill_holes"]
    cfg.mesh.tsdf.fill_holes = 2.0  # the small holes filled from the Poisson surface
    assert get_mesh_method("tsdf").reads(cfg)["mesh.poisson.depth"] == 7
    f, p = get_mesh_method("field"), get_mesh_method("poisson")
    assert (f.needs_field, f.closed, p.needs_field, p.closed) == (True, True, False, False)


@pytest.mark.parametrize("name", ["field", "poisson", "tsdf"])
def test_every_declared_option_is_an_option_of_the_config(name):
    cfg = preset("fast")
    cfg.mesh.tsdf.fill_holes = 1.0
    for key, value in get_mesh_method(name).reads(cfg).items():
        assert key.startswith("mesh.") and value is not None


def test_a_closed_method_of_the_field_takes_the_field_methods_rules():
    cfg = preset("fast")
    cfg.mesh.method, cfg.mesh.watertight = "test-closed-field", True
    validate_config(cfg)  # closed: the watertight mesh is its
    assert options.mesh_method(cfg).reads(cfg) == {"mesh.resolution": cfg.mesh.resolution}
    cfg.mesh.watertight, cfg.mesh.fit_points = False, 200
    assert options.wants_mesh_fit(cfg)  # a surface of the field: fitted to the points
    assert options.mesh_from_points(cfg) is None
    cfg.mesh.method = "test-open-field"
    cfg.mesh.watertight = True
    with pytest.raises(InputError, match="mesh.watertight = True with mesh.method = "
                                         "test-open-field: the test-open-field method gives no "
                                         "closed surface .* use mesh.method=field or "
                                         "test-closed-field"):
        validate_config(cfg)
    cfg.mesh.watertight = False
    cfg.train.mode = "mvs-only"
    with pytest.raises(InputError, match=r"mvs-only fits no field .* a method of the points "
                                         r"\(poisson, tsdf"):
        validate_config(cfg)


def _string_constants(path: Path) -> set[str]:
    return {n.value for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.Constant)
            and isinstance(n.value, str)}


@pytest.mark.parametrize("module", ["config/validate.py", "pipeline/options.py"])
def test_validation_and_the_rules_name_no_builtin_mesh_method_or_field_kind(module):
    names = set(registered_mesh_methods()) | set(registered_field_kinds())
    found = _string_constants(Path(svolsdf.__file__).parent / module) & names
    assert not found, f"{module} compares {sorted(found)}: ask the registry entry instead"
