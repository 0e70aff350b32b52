"""The mesh method registry (`svolsdf.fusion.mesh_methods`): a method registered here, in the test
file alone, is accepted by the config and run by the mesh stage; an unregistered name is
refused naming the option."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from tiny_pipeline import make_tiny_scene, rerun_on_copy, tiny_cfg

from svolsdf.config import preset, validate_config
from svolsdf.errors import InputError
from svolsdf.fusion.mesh_methods import (
    MeshInputs,
    get_mesh_method,
    register_mesh_method,
    registered_mesh_methods,
)
from svolsdf.io.ply import read_ply
from svolsdf.pipeline import Pipeline

# the 12 triangles of a box whose corners are indexed by (x, y, z) bits
_BOX_FACES = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
              [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]


@register_mesh_method("test-box", needs_points=True)
def _box_around_the_points(m: MeshInputs):
    """The bounding box of the fused points."""
    lo, hi = m.points.min(0), m.points.max(0)
    corners = np.array([[(hi if i & 4 else lo)[0], (hi if i & 2 else lo)[1],
                         (hi if i & 1 else lo)[2]] for i in range(8)])
    return (torch.from_numpy(corners).float(), torch.tensor(_BOX_FACES, dtype=torch.int64),
            None)


def test_builtin_methods_are_registered_in_the_documented_order():
    assert registered_mesh_methods()[:3] == ["field", "poisson", "tsdf"]
    assert not get_mesh_method("field").needs_points
    assert get_mesh_method("poisson").needs_points
    assert get_mesh_method("tsdf").needs_points and get_mesh_method("tsdf").needs_observed


def test_a_registered_method_is_a_valid_choice():
    cfg = preset("fast")
    cfg.mesh.method = "test-box"
    validate_config(cfg)
    assert cfg.mesh.method == "test-box"


def test_an_unregistered_method_is_refused_naming_the_option():
    cfg = preset("fast")
    cfg.mesh.method = "no-such-method"
    with pytest.raises(InputError, match=r"mesh\.method = 'no-such-method': expected "
                                         r"one of 'field', 'poisson', 'tsdf'"):
        validate_config(cfg)
    with pytest.raises(InputError, match="unknown mesh method 'no-such-method'"):
        get_mesh_method("no-such-method")


@pytest.mark.slow
def test_a_registered_method_runs_as_the_mesh_stage(tmp_path_factory, tmp_path):
    """Only the mesh reruns with the toy method, which meshes the fused points; timing.json
    names it as the mesh's source."""
    scene = make_tiny_scene(tmp_path_factory.mktemp("syn") / "scene")
    out = tmp_path_factory.mktemp("run")
    Pipeline(tiny_cfg(scene), out, progress=False).run()
    p2 = rerun_on_copy(out, tmp_path / "box", mesh__method="test-box")
    assert set(p2.timing) - {"total"} == {"mesh"}, p2.timing
    timing = json.loads((tmp_path / "box" / "timing.json").read_text())
    assert timing["mesh"]["mesh_source"] == "test-box" == timing["mesh"]["method"]
    pts = read_ply(out / "points.ply")["points"]
    assert timing["mesh"]["points"] == len(pts)
    m = read_ply(tmp_path / "box" / "mesh.ply")
    assert len(m["faces"]) == 12
    assert np.allclose(m["points"].min(0), pts.min(0), atol=1e-4)
    assert np.allclose(m["points"].max(0), pts.max(0), atol=1e-4)
