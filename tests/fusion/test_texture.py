"""The texture atlas: each face's texels in its own half-cell, its corners' texture
coordinates on its texels, and the baked colours those of the photo where the face is seen."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from svolsdf.fusion.texture import atlas_layout, bake_atlas
from svolsdf.scene.cameras import Cameras


@pytest.mark.parametrize("n_faces, texels", [(1, None), (7, None), (50, 400), (301, None)])
def test_every_face_owns_the_texels_under_its_corners(n_faces, texels):
    uv, face, bary, S = atlas_layout(n_faces, max_size=512, texels=texels)
    assert uv.shape == (n_faces, 3, 2) and face.shape == (S, S) and bary.shape == (S, S, 3)
    assert set(np.unique(face)) <= set(range(-1, n_faces))
    assert set(range(n_faces)) <= set(np.unique(face))
    np.testing.assert_allclose(bary[face >= 0].sum(-1), 1.0)
    assert (bary >= 0).all()
    # a corner's texture coordinate falls on a texel of its own face (OBJ: v up)
    px = np.floor(uv[..., 0] * S).astype(int), np.floor((1 - uv[..., 1]) * S).astype(int)
    owner = face[px[1], px[0]]
    assert (owner == np.arange(n_faces)[:, None]).all()


def test_atlas_too_small_is_refused():
    with pytest.raises(ValueError, match="do not fit a 8 x 8 atlas"):
        atlas_layout(100, max_size=8)


def test_baked_colours_are_the_photo_where_each_face_is_seen():
    # a plane at z = 5 facing a camera at the origin, as a grid of triangles; the photo is red
    # on its left half and blue on its right
    s = np.linspace(-1.0, 1.0, 9)
    xx, yy = np.meshgrid(s, s)
    v = np.c_[xx.ravel(), yy.ravel(), np.full(81, 5.0)]
    i = np.arange(81).reshape(9, 9)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    f = np.r_[np.c_[a, b, c], np.c_[b, d, c]]
    K = torch.tensor([[[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]]], dtype=torch.float64)
    cams = Cameras(K, torch.eye(4, dtype=torch.float64)[None], 64, 48)
    img = torch.zeros(1, 3, 48, 64)
    img[0, 0, :, :32] = 1.0
    img[0, 2, :, 32:] = 1.0
    depth = torch.full((1, 48, 64), 5.0)
    uv, tex = bake_atlas(v, f, img, cams, depth)
    S = tex.shape[0]
    centre = v[f].mean(1)
    x = 60.0 * centre[:, 0] / 5.0 + 31.5  # the face centre's column in the photo
    c_uv = uv.mean(1)
    col = tex[np.floor((1 - c_uv[:, 1]) * S).astype(int), np.floor(c_uv[:, 0] * S).astype(int)]
    left, right = x < 31.5 - 4, x > 31.5 + 4
    assert left.any() and right.any()
    assert (col[left] == [255, 0, 0]).all() and (col[right] == [0, 0, 255]).all()


def test_textured_obj_opens_in_trimesh_with_its_texture(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    from svolsdf.io.ply import write_textured_obj

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    f = np.array([[0, 1, 2], [1, 3, 2]])
    uv, face, _, S = atlas_layout(len(f), max_size=64, max_cell=8)
    tex = np.zeros((S, S, 3), np.uint8)
    tex[face == 0] = [255, 0, 0]
    tex[face == 1] = [0, 255, 0]
    paths = write_textured_obj(tmp_path / "m.obj", v, f, uv, tex)
    assert [p.name for p in paths] == ["m.obj", "m.mtl", "m.png"]
    m = trimesh.load(tmp_path / "m.obj", process=False)
    assert isinstance(m.visual, trimesh.visual.TextureVisuals)
    assert m.visual.material.image.size == (S, S)
    # each face's corners sample its own colour
    cols = np.asarray(m.visual.to_color().vertex_colors)[:, :3]
    np.testing.assert_allclose(m.vertices[m.faces], v[f])
    assert (cols[m.faces[0]] == [255, 0, 0]).all() and (cols[m.faces[1]] == [0, 255, 0]).all()
