"""Tests of svolsdf.evaluate.chamfer: known values, exact greedy downsampling, the obs mask, the
plane, the real ObsMask file, and agreement with a slow transcription of the DTUeval-python
protocol (docs/method.md 8.1)."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement
from scipy.io import savemat

from conftest import shared_path
from svolsdf.errors import InputError
from svolsdf.evaluate import points as points_module
from svolsdf.evaluate.chamfer import (
    ObsMask,
    chamfer_fscore,
    dtu_chamfer,
    dtu_chamfer_arrays,
    find_dtu_files,
    greedy_radius_downsample,
    load_obs_mask,
    load_plane,
    mesh_density,
    mesh_surface_points,
    nn_distances,
    obs_mask_filter,
    sample_mesh_surface,
    shuffle_rows,
)

# --------------------------------------------------------------------------- slow references


def slow_greedy(points: np.ndarray, radius: float) -> np.ndarray:
    """The reference's sequential loop with brute-force neighbourhoods."""
    keep = np.ones(len(points), dtype=bool)
    for i in range(len(points)):
        if keep[i]:
            keep[np.linalg.norm(points - points[i], axis=1) <= radius] = False
            keep[i] = True
    return keep


def slow_nn(query: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return np.array([np.sqrt(((ref - q) ** 2).sum(1)).min() for q in query])


def slow_sample_triangles(vertices, faces, density):
    """Per-triangle barycentric grids with np.mgrid, one triangle at a time."""
    out = [vertices]
    for f in faces:
        v0, v1, v2 = vertices[f]
        e1, e2 = v1 - v0, v2 - v0
        l1, l2 = np.linalg.norm(e1), np.linalg.norm(e2)
        a2 = np.linalg.norm(np.cross(e1, e2))
        if a2 <= 0:
            continue
        thr = density * np.sqrt(l1 * l2 / a2)
        n1, n2 = np.floor(l1 / thr), np.floor(l2 / thr)
        c = np.mgrid[: n1 + 1, : n2 + 1].astype(np.float64) + 0.5
        c[0] /= max(n1, 1e-7)
        c[1] /= max(n2, 1e-7)
        c = c.reshape(2, -1).T
        k = c[c.sum(1) < 1]
        out.append(e1 * k[:, :1] + e2 * k[:, 1:] + v0)
    return np.concatenate(out)


def slow_dtu(points, stl, mask, bb, res, plane, seed, mode="pcd", faces=None, density=0.2,
             patch=60.0, max_dist=20.0):
    """A plain transcription of the DTUeval-python steps (loops, brute-force distances).

    Step by step as the community script (jzhangbs/DTUeval-python ``eval.py``, used by the
    MVSNet / NeuS / VolSDF / S-VolSDF repositories): mesh mode samples every non-degenerate
    triangle on a barycentric grid (``np.mgrid`` + 0.5, divided by max(n, 1e-7), kept where
    c1 + c2 < 1) after the vertices; the cloud is shuffled with ``default_rng().shuffle(axis=0)``
    (seeded here); greedy removal visits the points in order and drops every neighbour within
    ``radius`` inclusive (sklearn's ``radius_neighbors`` includes the boundary), keeping the
    visitor; BB is cast to float32 and data_in is BB_min - patch <= p < BB_max + 2 patch on all
    axes; the voxel index is ``np.around((p - BB_min) / Res)`` and must lie in the grid with
    ObsMask true (data_in_obs); accuracy is the mean of the data_in_obs -> STL distances below
    max_dist, completeness that of the STL points with P . [x, y, z, 1] > 0 -> data_in, and
    overall their mean.
    """
    data = slow_sample_triangles(points, faces, density) if mode == "mesh" else points.copy()
    np.random.default_rng(seed).shuffle(data, axis=0)
    data = data[slow_greedy(data, density)]
    bb = bb.astype(np.float32)
    data_in, data_in_obs = [], []
    for p in data:
        if all(bb[0, a] - patch <= p[a] < bb[1, a] + 2 * patch for a in range(3)):
            data_in.append(p)
            g = [int(np.around((p[a] - bb[0, a]) / res)) for a in range(3)]
            if all(0 <= g[a] < mask.shape[a] for a in range(3)) and mask[g[0], g[1], g[2]]:
                data_in_obs.append(p)
    data_in, data_in_obs = np.array(data_in), np.array(data_in_obs)
    above = np.array([plane[:3] @ s + plane[3] > 0 for s in stl])
    d2s = slow_nn(data_in_obs, stl)
    s2d = slow_nn(stl[above], data_in)
    acc = d2s[d2s < max_dist].mean()
    comp = s2d[s2d < max_dist].mean()
    return acc, comp, (acc + comp) / 2


# --------------------------------------------------------------------------- fixtures


def write_ply(path, pts):
    v = np.zeros(len(pts), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    v["x"], v["y"], v["z"] = pts.T
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))


def dtu_like(rng, n_stl=1500, n_pred=1200):
    """A tiny DTU-like scene: a bumpy surface over a floor, an obs mask, a plane z > -4."""
    bb = np.array([[0, 0, -5], [20, 20, 10]], dtype=np.int16)
    res = 1
    shape = tuple(int(s) for s in (bb[1] - bb[0]) // res + 1)
    mask = np.zeros(shape, dtype=np.uint8)
    mask[2:18, 2:19, :] = 1  # observed except a border
    xy = rng.uniform(-2, 22, size=(n_stl, 2))
    z = np.sin(xy[:, 0] / 3) + 0.5 * np.cos(xy[:, 1] / 4)
    stl = np.c_[xy, z]
    floor = np.c_[rng.uniform(0, 20, size=(200, 2)), np.full(200, -6.0)]  # below the plane
    stl = np.concatenate([stl, floor])
    pick = rng.choice(n_stl, n_pred)
    pred = stl[pick] + rng.normal(scale=0.3, size=(n_pred, 3))
    pred = np.concatenate([pred, rng.uniform([-30, -30, -30], [100, 100, 100], size=(40, 3))])
    plane = np.array([0.0, 0.0, 1.0, 4.0])  # above: z > -4
    return pred, stl, mask, bb, res, plane


def write_dtu_dir(root, scan, stl, mask, bb, res, plane, plane_scan=None, sub=""):
    base = root / sub if sub else root
    (base / "ObsMask").mkdir(parents=True)
    (base / "Points" / "stl").mkdir(parents=True)
    savemat(base / "ObsMask" / f"ObsMask{scan}_10.mat",
            {"ObsMask": mask, "BB": bb, "Res": np.array([[res]], dtype=np.uint8)})
    savemat(base / "ObsMask" / f"Plane{plane_scan or scan}.mat", {"P": plane.reshape(4, 1)})
    write_ply(base / "Points" / "stl" / f"stl{scan:03d}_total.ply", stl)


# --------------------------------------------------------------------------- generic Chamfer


def test_shifted_sets_chamfer_equals_offset():
    g = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0), [0.0]), -1).reshape(-1, 3)
    r = chamfer_fscore(g + [0, 0, 0.3], g, threshold=0.5)
    assert r["accuracy"] == pytest.approx(0.3)
    assert r["completeness"] == pytest.approx(0.3)
    assert r["overall"] == pytest.approx(0.3)
    assert r["fscore"] == 1.0
    r = chamfer_fscore(g + [0, 0, 0.3], g, threshold=0.2)
    assert r["precision"] == 0 and r["recall"] == 0 and r["fscore"] == 0


def test_fscore_partial_coverage_and_max_dist():
    gt = np.c_[np.arange(10.0), np.zeros(10), np.zeros(10)]
    pred = gt[:5]
    r = chamfer_fscore(pred, gt, threshold=0.5)
    assert r["precision"] == 1.0 and r["recall"] == 0.5
    assert r["fscore"] == pytest.approx(2 / 3)
    assert r["accuracy"] == 0.0
    assert r["completeness"] == pytest.approx(np.mean([0, 0, 0, 0, 0, 1, 2, 3, 4, 5]))
    r = chamfer_fscore(pred, gt, threshold=0.5, max_dist=3)  # drops the 3, 4, 5 distances
    assert r["completeness"] == pytest.approx(np.mean([0, 0, 0, 0, 0, 1, 2]))


def test_chamfer_fscore_downsample_and_errors():
    rng = np.random.default_rng(1)
    gt = rng.random((500, 3))
    r = chamfer_fscore(np.concatenate([gt, gt]), gt, threshold=0.01, downsample=1e-6)
    assert r["overall"] == 0.0 and r["fscore"] == 1.0
    with pytest.raises(InputError, match="0 predicted"):
        chamfer_fscore(np.zeros((0, 3)), gt, threshold=0.1)
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        chamfer_fscore(np.zeros((5, 2)), gt, threshold=0.1)


# --------------------------------------------------------------------------- building blocks


@pytest.mark.parametrize("radius", [0.05, 0.1, 0.3])
def test_greedy_downsampling_matches_sequential_loop(radius):
    rng = np.random.default_rng(int(radius * 100))
    p = rng.random((1500, 3))
    p = np.concatenate([p, p[:100]])  # exact duplicates are removed
    rng.shuffle(p)
    keep = greedy_radius_downsample(p, radius)
    np.testing.assert_array_equal(keep, slow_greedy(p, radius))


@pytest.mark.parametrize("chunk", [1, 97, 600, 10_000])
def test_greedy_downsampling_in_chunks_keeps_the_same_set(chunk):
    """Visiting the cloud ``chunk`` points at a time (the memory bound for dense clouds) keeps
    exactly the points one pass and the sequential loop keep."""
    rng = np.random.default_rng(5)
    p = rng.random((1500, 3))
    p = np.concatenate([p, p[:80], p[:3] + 0.03])  # duplicates and near-duplicates
    rng.shuffle(p)
    keep = greedy_radius_downsample(p, 0.1, chunk=chunk)
    np.testing.assert_array_equal(keep, slow_greedy(p, 0.1))
    with pytest.raises(ValueError, match="chunk"):
        greedy_radius_downsample(p, 0.1, chunk=0)


def test_mesh_sampling_matches_per_triangle_grids():
    rng = np.random.default_rng(2)
    v = rng.uniform(0, 3, size=(30, 3))
    f = rng.integers(0, 30, size=(40, 3))
    f[0] = [1, 1, 2]  # degenerate: skipped
    fast = sample_mesh_surface(v, f, density=0.2, max_batch=500)  # several batches
    slow = slow_sample_triangles(v, f, 0.2)
    assert fast.shape == slow.shape and len(fast) > 500
    np.testing.assert_array_equal(fast, slow)


def test_obs_mask_indexing_on_hand_built_mat(tmp_path):
    mask = np.zeros((5, 6, 7), dtype=np.uint8)
    mask[2, 3, 1] = 1
    savemat(tmp_path / "ObsMask1_10.mat", {"ObsMask": mask, "BB": np.array(
        [[10, 20, 30], [14, 25, 36]], dtype=np.int16), "Res": np.array([[1]], dtype=np.uint8)})
    obs = load_obs_mask(tmp_path / "ObsMask1_10.mat")
    assert obs.mask.dtype == bool and obs.bb.dtype == np.float32 and obs.res == 1.0
    pts = np.array([
        [12.4, 23.4, 31.0],   # rounds to (2, 3, 1): observed
        [12.5, 22.5, 30.5],   # half to even: (2, 2, 0): not observed
        [11.5, 23.0, 31.0],   # (2, 3, 1) via round-half-even of 1.5 -> 2: observed
        [12.6, 23.0, 31.0],   # (3, 3, 1): not observed
        [9.0, 23.0, 31.0],    # index -1: in the BB margin, outside the grid
        [-50.0, 20.0, 30.0],  # BB_min - 60 <= p: inside the margin
        [-50.1, 20.0, 30.0],  # below BB_min - 60
        [133.9, 20.0, 30.0],  # < BB_max + 120
        [134.0, 20.0, 30.0],  # not < BB_max + 120
    ])
    in_bb, in_obs = obs_mask_filter(pts, obs)
    np.testing.assert_array_equal(in_bb, [1, 1, 1, 1, 1, 1, 0, 1, 0])
    np.testing.assert_array_equal(in_obs, [1, 0, 1, 0, 0, 0, 0, 0, 0])


def test_plane_filters_completeness_only():
    obs = ObsMask(mask=np.ones((11, 11, 11), bool), bb=np.array([[0, 0, 0], [10, 10, 10]],
                                                                   np.float32), res=1.0)
    g = np.stack(np.meshgrid(np.arange(0, 10, 0.5), np.arange(0, 10, 0.5), [5.0]), -1)
    top = g.reshape(-1, 3)
    below = top - [0, 0, 4]  # 4 mm under the prediction, under the plane z = 3
    stl = np.concatenate([top, below])
    plane = np.array([0, 0, 1.0, -3.0])
    r = dtu_chamfer_arrays(top, stl, obs, plane)
    assert r["completeness"] == 0.0 and r["accuracy"] == 0.0
    r = dtu_chamfer_arrays(top, stl, obs, np.array([0, 0, 1.0, 0.0]))  # everything above
    assert r["completeness"] == pytest.approx(2.0)


def test_find_files_layouts_and_errors(tmp_path):
    rng = np.random.default_rng(3)
    _, stl, mask, bb, res, plane = dtu_like(rng, 50, 10)
    write_dtu_dir(tmp_path / "a", 82, stl, mask, bb, res, plane, plane_scan=83)
    files = find_dtu_files(tmp_path / "a", 82)
    assert files.plane.name == "Plane83.mat"
    write_dtu_dir(tmp_path / "b", 9, stl, mask, bb, res, plane, sub="DTU_MVS_Data")
    assert find_dtu_files(tmp_path / "b", 9).stl.name == "stl009_total.ply"
    np.testing.assert_allclose(load_plane(find_dtu_files(tmp_path / "b", 9).plane), plane)
    with pytest.raises(InputError, match="ObsMask10_10.mat"):
        find_dtu_files(tmp_path / "b", 10)
    (tmp_path / "b" / "DTU_MVS_Data" / "ObsMask" / "Plane9.mat").unlink()
    with pytest.raises(InputError, match="Plane9.mat"):
        dtu_chamfer(stl, tmp_path / "b", 9)


def test_real_obsmask_loads():
    path = shared_path("data", "dtu_raw", "ObsMask", "ObsMask9_10.mat")
    obs = load_obs_mask(path)
    assert obs.mask.shape == (204, 382, 340) and obs.mask.dtype == bool
    assert obs.bb.dtype == np.float32 and obs.bb.shape == (2, 3)
    np.testing.assert_array_equal(obs.bb, [[-73, -197, 472], [129, 183, 810]])
    assert obs.res == 1.0 and obs.mask.any() and not obs.mask.all()


@pytest.fixture
def always_sort(monkeypatch):
    """Force the Morton-sorted KD-tree paths (normally only for >= 20k points)."""
    monkeypatch.setattr(points_module, "_SORT_MIN", 0)


@pytest.mark.parametrize("radius", [0.05, 0.3])
def test_greedy_downsampling_sorted_tree_path(always_sort, radius):
    rng = np.random.default_rng(11)
    p = rng.random((1200, 3))
    p = np.concatenate([p, p[:50], rng.uniform(50, 60, size=(5, 3))])  # duplicates, outliers
    rng.shuffle(p)
    np.testing.assert_array_equal(greedy_radius_downsample(p, radius), slow_greedy(p, radius))


def test_nn_distances_sorted_path_is_exact(always_sort):
    rng = np.random.default_rng(12)
    ref = rng.random((700, 3))
    q = np.concatenate([rng.random((500, 3)), rng.uniform(5, 9, size=(5, 3))])
    np.testing.assert_allclose(nn_distances(q, ref), slow_nn(q, ref), rtol=0, atol=1e-12)
    d = nn_distances(q, ref, upper_bound=1.0)
    assert np.isinf(d[-5:]).all()
    np.testing.assert_allclose(d[:-5], slow_nn(q[:-5], ref), rtol=0, atol=1e-12)


def test_shuffle_rows_equals_generator_shuffle():
    x = np.random.default_rng(13).random((1001, 3))
    want = x.copy()
    np.random.default_rng(42).shuffle(want, axis=0)
    np.testing.assert_array_equal(shuffle_rows(x, 42), want)
    assert not np.array_equal(shuffle_rows(x, 42), x)


# --------------------------------------------------------------------------- reference agreement


def test_dtu_protocol_agrees_with_slow_reference_pcd(tmp_path):
    rng = np.random.default_rng(4)
    pred, stl, mask, bb, res, plane = dtu_like(rng)
    write_dtu_dir(tmp_path, 24, stl, mask, bb, res, plane)
    stl32 = stl.astype(np.float32).astype(np.float64)  # as stored in the PLY
    ours = dtu_chamfer(pred, tmp_path, 24, seed=7)
    ref = slow_dtu(pred, stl32, mask, bb, res, plane, seed=7)
    for key, want in zip(("accuracy", "completeness", "overall"), ref, strict=True):
        assert ours[key] == pytest.approx(want, rel=0.01)
    assert 0.1 < ours["overall"] < 5


def test_dtu_protocol_agrees_with_slow_reference_mesh():
    rng = np.random.default_rng(5)
    _, stl, mask, bb, res, plane = dtu_like(rng, n_stl=800)
    # A coarse triangulated patch of the surface: 3x3 quads over [4, 16]^2.
    xs = np.linspace(4, 16, 4)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    v = np.c_[gx.ravel(), gy.ravel(), np.sin(gx.ravel() / 3) + 0.5 * np.cos(gy.ravel() / 4)]
    f = []
    for i in range(3):
        for j in range(3):
            a, b, c, d = i * 4 + j, i * 4 + j + 1, (i + 1) * 4 + j, (i + 1) * 4 + j + 1
            f += [[a, b, d], [a, d, c]]
    f = np.array(f)
    obs = ObsMask(mask.astype(bool), bb.astype(np.float32), float(res))
    ours = dtu_chamfer_arrays(v, stl, obs, plane, mode="mesh", faces=f, seed=3,
                              downsample_density=0.5)
    ref = slow_dtu(v, stl, mask, bb, res, plane, seed=3, mode="mesh", faces=f, density=0.5)
    for key, want in zip(("accuracy", "completeness", "overall"), ref, strict=True):
        assert ours[key] == pytest.approx(want, rel=0.01)


@pytest.mark.parametrize("sort", [False, True])
def test_dtu_protocol_agrees_on_the_real_obsmask(monkeypatch, sort):
    """Small clouds inside scan 9's real observation mask (no STL exists: a noisy copy of the
    prediction stands in), protocol vs the slow transcription, with and without sorting."""
    obs = load_obs_mask(shared_path("data", "dtu_raw", "ObsMask", "ObsMask9_10.mat"))
    if sort:
        monkeypatch.setattr(points_module, "_SORT_MIN", 0)
    rng = np.random.default_rng(14)
    # A 20 x 20 mm patch near the middle of the box, a mix of observed and unobserved voxels.
    centre = obs.bb.mean(0).astype(np.float64)
    xy = rng.uniform(-10, 10, size=(900, 2))
    pred = centre + np.c_[xy, 0.2 * xy[:, 0] + rng.normal(scale=0.3, size=900)]
    pred = np.concatenate([pred, pred[:30] + 0.05, centre + rng.uniform(-80, 80, size=(40, 3))])
    stl = pred[rng.choice(len(pred) - 40, 700)] + rng.normal(scale=0.4, size=(700, 3))
    plane = np.array([0.0, 0.0, 1.0, -centre[2] + 5.0])  # above: z > centre_z - 5
    ours = dtu_chamfer_arrays(pred, stl, obs, plane, seed=9)
    ref = slow_dtu(pred, stl, obs.mask, obs.bb, obs.res, plane, seed=9)
    _, in_obs = obs_mask_filter(pred, obs)
    assert 0.1 < in_obs.mean() < 0.95  # both branches of the mask are exercised
    for key, want in zip(("accuracy", "completeness", "overall"), ref, strict=True):
        assert ours[key] == pytest.approx(want, rel=0.01)


# --------------------------------------------------------------------------- meshes: by surface


def _grid_mesh(n: int, size: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """The square [0, size]^2 at z = 0 as an n x n grid of quads, two triangles each:
    (V, 3) vertices, (F, 3) faces."""
    xs = np.linspace(0, size, n + 1)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    v = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    b, c, d = a + 1, a + n + 1, a + n + 2
    return v, np.concatenate([np.c_[a, b, d], np.c_[a, d, c]])


def _subdivide(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle into four at its edges' midpoints: 4x the faces, the same surface."""
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    edges, inv = np.unique(e, axis=0, return_inverse=True)
    m = inv.reshape(3, -1) + len(v)  # midpoints of edges 01, 12, 20
    v2 = np.concatenate([v, (v[edges[:, 0]] + v[edges[:, 1]]) / 2])
    a, b, c = f.T
    ab, bc, ca = m
    return v2, np.concatenate([np.c_[a, ab, ca], np.c_[ab, b, bc], np.c_[ca, bc, c],
                               np.c_[ab, bc, ca]])


def _icosphere(level: int) -> tuple[np.ndarray, np.ndarray]:
    """The unit sphere: an icosahedron subdivided ``level`` times, vertices on the sphere."""
    t = (1 + 5 ** 0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
                 dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]])
    for _ in range(level):
        v, f = _subdivide(v, f)
    return v / np.linalg.norm(v, axis=1, keepdims=True), f


def _surface_score(v, f, gt, density):
    """The generic protocol's Chamfer of a mesh by its surface (as `svolsdf evaluate
    --gt-points` scores it)."""
    return chamfer_fscore(mesh_surface_points(v, f, density), gt, threshold=0.1)


def _vertex_score(v, gt):
    """The Chamfer of a mesh by its vertices: how meshes were scored before."""
    return chamfer_fscore(v, gt, threshold=0.1)


def test_a_flap_past_the_ground_truth_scores_worse_by_surface_not_by_vertices():
    """A plane mesh scored against its own (dense) ground truth, with and without a large
    triangle extrapolated past its edge (one new vertex) or bridging a hole of the ground truth
    (no new vertex): the surface scorer charges the flap's area; vertex scoring, the old way,
    barely sees the first (one vertex among 1681) and cannot see the second at all."""
    v, f = _grid_mesh(40)
    g = np.arange(0.025, 10, 0.05)
    gt = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), -1).reshape(-1, 3)
    density = 0.05
    # past the silhouette: a triangle on the edge x = 10, its tip 5 beyond it
    v_flap = np.concatenate([v, [[15.0, 5.0, 0.0]]])
    corner = lambda i, j: i * 41 + j  # noqa: E731
    f_flap = np.concatenate([f, [[corner(40, 0), len(v), corner(40, 40)]]])
    base, flap = _surface_score(v, f, gt, density), _surface_score(v_flap, f_flap, gt, density)
    assert base["accuracy"] < 0.03 and base["overall"] < 0.03
    assert flap["accuracy"] > base["accuracy"] + 0.2  # a fifth of the surface, ~1.7 away
    assert flap["overall"] > base["overall"] + 0.1
    assert flap["completeness"] == pytest.approx(base["completeness"], abs=0.01)
    old_base, old_flap = _vertex_score(v, gt), _vertex_score(v_flap, gt)
    assert abs(old_flap["overall"] - old_base["overall"]) < 0.01  # the old way did not see it
    # over a hole: the ground truth without [3, 7]^2, the mesh's faces there replaced by two
    # triangles on the hole's corners (the same vertices)
    hole = ((gt[:, :2] > 3) & (gt[:, :2] < 7)).all(1)
    cent = v[f].mean(1)[:, :2]
    outside = ~((cent > 3) & (cent < 7)).all(1)
    a, b, c, d = corner(12, 12), corner(28, 12), corner(12, 28), corner(28, 28)
    f_open = f[outside]
    f_bridged = np.concatenate([f_open, [[a, b, d], [a, d, c]]])
    opened = _surface_score(v, f_open, gt[~hole], density)
    bridged = _surface_score(v, f_bridged, gt[~hole], density)
    assert bridged["accuracy"] > opened["accuracy"] + 0.05  # 16 % of the area, ~0.7 away
    assert bridged["overall"] > opened["overall"] + 0.025
    assert _vertex_score(v, gt[~hole]) == _vertex_score(v, gt[~hole])  # same vertices: blind


def test_subdividing_a_mesh_does_not_change_its_score():
    """The same surface with 4x and 16x the vertices scores the same, within 1.5 %; scored by its
    vertices (the old way), the same subdivision moves the Chamfer by a factor of 2.6. (With
    DTUeval-python's grids, ``oversample=1``, the completeness moves by 7 %.)"""
    v, f = _icosphere(2)  # 320 faces, vertices on the unit sphere
    rng = np.random.default_rng(0)
    gt = rng.normal(size=(40_000, 3))
    gt /= np.linalg.norm(gt, axis=1, keepdims=True)
    density = 0.02
    scores, old = [], []
    for _ in range(3):
        scores.append(_surface_score(v, f, gt, density))
        old.append(_vertex_score(v, gt))
        v, f = _subdivide(v, f)
    for s in scores[1:]:
        for k in ("accuracy", "completeness", "overall"):
            assert s[k] == pytest.approx(scores[0][k], rel=0.015), k
    assert old[2]["accuracy"] > 1.5 * old[0]["accuracy"]  # midpoints lie inside the sphere
    assert old[0]["overall"] > 2.5 * old[2]["overall"]  # and fill the gaps between vertices


def test_mesh_density_rule_and_the_dtu_mesh_mode():
    """DTU: 0.2 mm; scale-free protocols: 0.1 % of the ground truth's diagonal (0.2 mm on a
    200 mm object), the radius at which the synthetic protocol evens out its clouds; DTU's
    mesh mode scores exactly `mesh_surface_points`."""
    assert mesh_density() == 0.2
    assert mesh_density(200.0) == pytest.approx(0.2)
    assert mesh_density(150.0) == pytest.approx(0.15)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(InputError, match="diagonal"):
            mesh_density(bad)
    with pytest.raises(InputError, match="density"):
        mesh_surface_points(*_grid_mesh(2), density=0.0)
    v, f = _grid_mesh(3)
    pts = mesh_surface_points(v, f, 0.5, seed=3)
    # evenly spread: no two points within the density, every grid point (at half of it) within
    # it of one
    assert len(pts) > 100
    d, _ = points_module._kdtree(pts).query(pts, k=2)
    assert d[:, 1].min() > 0.5
    assert nn_distances(sample_mesh_surface(v, f, 0.25), pts).max() <= 0.5 + 1e-9
    # the DTU protocol's mesh mode is the scorer on DTUeval-python's grids (oversample 1)
    rng = np.random.default_rng(5)
    _, stl, mask, bb, res, plane = dtu_like(rng, n_stl=300)
    obs = ObsMask(mask.astype(bool), bb.astype(np.float32), float(res))
    v, f = _grid_mesh(4, size=16.0)
    dtu = dtu_chamfer_arrays(v, stl, obs, plane, mode="mesh", faces=f, seed=3,
                             downsample_density=0.5)
    via = dtu_chamfer_arrays(mesh_surface_points(v, f, 0.5, seed=3, oversample=1), stl, obs,
                             plane, downsample_density=0.5, seed=4)  # already even: kept as is
    assert dtu == pytest.approx(via, rel=1e-12)


def test_only_the_scorer_samples_a_mesh():
    """Every place that scores a mesh goes through `mesh_surface_points` (or
    `synthetic_chamfer(..., faces=)`, which does): no module of the package or the benchmarks
    samples triangles itself."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    users = [p.relative_to(root).as_posix()
             for top in ("src", "benchmarks") for p in sorted((root / top).rglob("*.py"))
             if "sample_mesh_surface(" in p.read_text()]
    assert users == ["src/svolsdf/evaluate/chamfer.py"]
