"""Chamfer distances: the DTU protocol (docs/method.md 8.1) and a generic two-way Chamfer / F-score.

The DTU protocol follows the community's DTUeval-python script step for step (the protocol the
S-VolSDF paper reports): seeded random shuffle, greedy 0.2 mm radius downsampling, the observation
mask (``ObsMask{scan}_10.mat``: ``ObsMask``, ``BB``, ``Res``) with a 60 mm patch, the ground plane
(``Plane{scan}.mat``) for completeness, a 20 mm cut-off, and overall = (accuracy + completeness)
/ 2. All distances are in the input's world units (DTU: millimetres).

The point-cloud building blocks (nearest neighbours, the seeded shuffle, the exact greedy
radius downsampling and how they are made fast) live in `svolsdf.evaluate.points`; the names are
re-exported here. A mesh is scored by its surface (`mesh_surface_points`), never its vertices.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.io import loadmat

from svolsdf.errors import InputError
from svolsdf.evaluate.points import (  # the building blocks; re-exported for existing callers
    _check_points,
    checked_ground_truth,
    greedy_radius_downsample,
    nn_distances,
    shuffle_rows,
)

__all__ = [
    "DTUFiles",
    "ObsMask",
    "chamfer_fscore",
    "dtu_chamfer",
    "dtu_chamfer_arrays",
    "find_dtu_files",
    "greedy_radius_downsample",
    "load_obs_mask",
    "load_plane",
    "mesh_density",
    "mesh_surface_points",
    "nn_distances",
    "obs_mask_filter",
    "sample_mesh_surface",
    "shuffle_rows",
]

log = logging.getLogger(__name__)

#: DTU scans whose plane file is another scan's (docs/method.md 8.1: scan 82 uses Plane83).
PLANE_OVERRIDES = {82: 83}

#: The DTU protocol's mesh sampling spacing and downsampling radius, mm (docs/method.md 8.1).
DTU_DENSITY = 0.2

#: The scale-free protocols' mesh sampling spacing, as a fraction of the ground truth's
#: bounding-box diagonal (`mesh_density`).
MESH_DENSITY_FRACTION = 0.001


# --------------------------------------------------------------------------- mesh surface

def sample_mesh_surface(vertices: np.ndarray, faces: np.ndarray, density: float = 0.2,
                        max_batch: int = 4_000_000) -> np.ndarray:
    """Points on a triangle mesh at a given spacing, as the DTU mesh mode does (docs/method.md 8.1).

    Per triangle (v0, v1, v2) with edges e1 = v1 - v0, e2 = v2 - v0 of lengths l1, l2 and
    doubled area A2 = |e1 x e2|: thr = density * sqrt(l1 l2 / A2), n_k = floor(l_k / thr), and the
    barycentric grid c = ((i + 0.5) / n1, (j + 0.5) / n2) for i = 0..n1, j = 0..n2 with c1 + c2 < 1
    gives the points v0 + c1 e1 + c2 e2. Zero-area triangles are skipped. The vertices themselves
    are included, as in the reference script. To score a mesh use `mesh_surface_points`, which
    evens these points out.

    Args:
        vertices: (V, 3) float vertex positions.
        faces: (F, 3) int vertex indices.
        density: sample spacing (DTU: 0.2 mm).
        max_batch: candidate grid points generated at once (bounds memory).

    Returns:
        (V + S, 3) float64: the vertices, then the S samples.
    """
    vertices = _check_points("vertices", vertices)
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError(f"faces: expected an (F, 3) int array, got shape {faces.shape}")
    if len(faces) == 0:
        return vertices.copy()
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(f"faces index vertices 0..{len(vertices) - 1} but hold "
                         f"{faces.min()}..{faces.max()}")
    tri = vertices[faces]
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    l1 = np.linalg.norm(e1, axis=-1)
    l2 = np.linalg.norm(e2, axis=-1)
    a2 = np.linalg.norm(np.cross(e1, e2), axis=-1)
    ok = a2 > 0
    e1, e2, v0, l1, l2, a2 = e1[ok], e2[ok], tri[ok, 0], l1[ok], l2[ok], a2[ok]
    thr = density * np.sqrt(l1 * l2 / a2)
    n1 = np.floor(l1 / thr)
    n2 = np.floor(l2 / thr)
    cand = ((n1 + 1) * (n2 + 1)).astype(np.int64)
    d1 = np.maximum(n1, 1e-7)
    d2 = np.maximum(n2, 1e-7)
    out = [vertices]
    ends = np.cumsum(cand)
    start_t = 0
    while start_t < len(cand):
        base = ends[start_t - 1] if start_t else 0
        stop_t = int(np.searchsorted(ends, base + max_batch, side="right"))
        stop_t = max(stop_t, start_t + 1)
        c = cand[start_t:stop_t]
        t = np.repeat(np.arange(start_t, stop_t), c)
        offs = np.repeat(np.cumsum(c) - c, c)
        local = np.arange(len(t), dtype=np.int64) - offs
        cols = (n2[t] + 1).astype(np.int64)
        i = (local // cols).astype(np.float64)
        j = (local % cols).astype(np.float64)
        k1 = (i + 0.5) / d1[t]
        k2 = (j + 0.5) / d2[t]
        sel = k1 + k2 < 1
        t, k1, k2 = t[sel], k1[sel, None], k2[sel, None]
        out.append(e1[t] * k1 + e2[t] * k2 + v0[t])
        start_t = stop_t
    return np.concatenate(out, axis=0)


def mesh_density(diag: float | None = None) -> float:
    """The spacing at which a mesh's surface is scored (docs/method.md 8.1, 8.2).

    The DTU protocol (``diag`` None): 0.2 mm, the radius at which it evens out every cloud and
    the spacing at which its mesh mode samples triangles. The scale-free protocols (synthetic
    scenes, the DTU pseudo ground truth of the benchmarks, ``--gt-points``): 0.1 % of the
    ground truth's bounding-box diagonal (`MESH_DENSITY_FRACTION`). That is the radius at which
    the synthetic protocol evens out every cloud (`svolsdf.evaluate.synthetic.truncated_chamfer`:
    a fifth of its F-score threshold of 0.5 %), the role 0.2 mm plays in DTU's, and about the
    same fraction of the object: 0.2 mm of a DTU object some 200 mm across (a synthetic scene
    on DTU's cameras fills 60 % of scan 65's unit sphere of radius 165 mm: 200 mm). A mesh is
    therefore evened out exactly as a point cloud is, so that a mesh / points ratio compares
    like with like; a finer spacing would only be thinned again by the protocol.

    Args:
        diag: the ground truth's bounding-box diagonal (> 0), or None for DTU.

    Returns:
        the spacing, in the ground truth's units.
    """
    if diag is None:
        return DTU_DENSITY
    if not (np.isfinite(diag) and diag > 0):
        raise InputError(f"mesh density: the ground truth's diagonal must be > 0, got {diag}")
    return float(diag) * MESH_DENSITY_FRACTION


def mesh_surface_points(vertices: np.ndarray, faces: np.ndarray, density: float = DTU_DENSITY,
                        seed: int | None = 0, oversample: int = 2) -> np.ndarray:
    """The points by which every protocol scores a mesh: its surface, evenly at ``density``.

    DTU's mesh mode (docs/method.md 8.1): the triangles sampled on barycentric grids
    (`sample_mesh_surface`, which adds the vertices), shuffled (``seed``) and greedily
    downsampled at radius ``density``. The points then cover the surface about evenly whatever
    the triangles: a large triangle over a hole or past a silhouette counts by its area, not by
    its three vertices. Vertices that no face uses are left out (the reference script would
    count them; meshes that svolsdf writes have none). Choose ``density`` with `mesh_density`.

    The grids are ``oversample`` times finer than ``density``: with 2 (the default) the greedy
    downsampling, not the triangulation, sets the spacing of the points, so that subdividing a
    mesh 16-fold moves its Chamfer by under 1 %. With 1 (DTUeval-python's mesh mode, which
    `dtu_chamfer_arrays` keeps to stay comparable with published numbers) a triangle whose edges
    are shorter than about twice ``density`` gets few or no grid points, so a finely
    triangulated mesh keeps fewer points, more of them vertices (its completeness a few % of
    ``density`` worse).

    Args:
        vertices: (V, 3) float vertex positions.
        faces: (F, 3) int triangles.
        density: downsampling radius and spacing of the points (> 0), in the vertices' units.
        seed: shuffle seed (None: unseeded, as the DTU reference script).
        oversample: the grids' spacing is ``density / oversample`` (>= 1).

    Returns:
        (N, 3) float64 points on the surface, no two within ``density`` of each other.
    """
    if not (np.isfinite(density) and density > 0):
        raise InputError(f"mesh density must be > 0, got {density}")
    if oversample < 1:
        raise InputError(f"mesh oversample must be >= 1, got {oversample}")
    vertices = _check_points("vertices", vertices)
    faces = np.asarray(faces)
    if faces.ndim == 2 and faces.shape[1] == 3 and len(faces) and faces.min() >= 0 \
            and faces.max() < len(vertices):
        # a vertex no face uses is not part of the surface (svolsdf's meshes have none)
        used, faces = np.unique(faces, return_inverse=True)
        vertices, faces = vertices[used], faces.reshape(-1, 3)
    data = shuffle_rows(sample_mesh_surface(vertices, faces, density / oversample), seed)
    return data[greedy_radius_downsample(data, density)]


# --------------------------------------------------------------------------- DTU files


@dataclass
class ObsMask:
    """DTU's observation mask (``ObsMask{scan}_10.mat``).

    Attributes:
        mask: (X, Y, Z) bool voxel grid; True where the structured-light scanner observed space.
        bb: (2, 3) float32 bounding box [min; max] in mm (the reference casts it to float32).
        res: voxel size in mm.
    """

    mask: np.ndarray
    bb: np.ndarray
    res: float


@dataclass
class DTUFiles:
    """The ground-truth files of one DTU scan.

    Attributes:
        obs_mask: ``ObsMask/ObsMask{scan}_10.mat``.
        plane: ``ObsMask/Plane{scan}.mat`` (scan 82: Plane83).
        stl: ``Points/stl/stl{scan:03d}_total.ply``.
    """

    obs_mask: Path
    plane: Path
    stl: Path


def find_dtu_files(dtu_dir: str | Path, scan: int) -> DTUFiles:
    """Locate a scan's ground-truth files under ``dtu_dir`` (or ``dtu_dir/DTU_MVS_Data``).

    Raises:
        InputError naming the first missing file.
    """
    from svolsdf.io.paths import input_dir

    dtu_dir = input_dir(dtu_dir, "DTU ground-truth folder")
    plane_scan = PLANE_OVERRIDES.get(int(scan), int(scan))
    rel = {
        "obs_mask": Path("ObsMask") / f"ObsMask{scan}_10.mat",
        "plane": Path("ObsMask") / f"Plane{plane_scan}.mat",
        "stl": Path("Points") / "stl" / f"stl{scan:03d}_total.ply",
    }
    found = {}
    for key, r in rel.items():
        for root in (dtu_dir, dtu_dir / "DTU_MVS_Data", dtu_dir / "SampleSet" / "MVS Data"):
            if (root / r).is_file():
                found[key] = root / r
                break
        else:
            raise InputError(
                f"{dtu_dir / r}: missing (DTU scan {scan} needs {rel['obs_mask']}, "
                f"{rel['plane']} and {rel['stl']} under {dtu_dir} or {dtu_dir / 'DTU_MVS_Data'})"
            )
    return DTUFiles(**found)


def _loadmat(path: Path, keys: tuple[str, ...]) -> dict:
    try:
        d = loadmat(str(path))
    except Exception as e:  # scipy raises several types for a bad file
        raise InputError(f"{path}: cannot read as a MATLAB .mat file ({e})") from None
    missing = [k for k in keys if k not in d]
    if missing:
        found = sorted(k for k in d if not k.startswith("__"))
        raise InputError(f"{path}: missing key(s) {missing}; found {found}")
    return d


def load_obs_mask(path: str | Path) -> ObsMask:
    """Read ``ObsMask{scan}_10.mat`` (keys ``ObsMask``, ``BB``, ``Res``)."""
    path = Path(path)
    d = _loadmat(path, ("ObsMask", "BB", "Res"))
    mask = np.asarray(d["ObsMask"]).astype(bool)
    bb = np.asarray(d["BB"]).astype(np.float32)
    if mask.ndim != 3 or bb.shape != (2, 3):
        raise InputError(f"{path}: expected a 3D ObsMask and a (2, 3) BB, got {mask.shape} "
                         f"and {bb.shape}")
    return ObsMask(mask=mask, bb=bb, res=float(np.asarray(d["Res"]).reshape(-1)[0]))


def load_plane(path: str | Path) -> np.ndarray:
    """Read ``Plane{scan}.mat`` (key ``P``) -> (4,) float64 plane; "above" is P . [x; 1] > 0."""
    path = Path(path)
    p = np.asarray(_loadmat(path, ("P",))["P"], dtype=np.float64).reshape(-1)
    if p.shape != (4,):
        raise InputError(f"{path}: P should hold 4 plane coefficients, got {p.size}")
    return p


def _read_ply_points(path: Path) -> np.ndarray:
    """(N, 3) float64 vertex positions of a PLY file (plyfile)."""
    from plyfile import PlyData

    try:
        v = PlyData.read(str(path))["vertex"].data
    except Exception as e:
        raise InputError(f"{path}: cannot read PLY vertices ({e})") from None
    return np.stack([np.asarray(v["x"], np.float64), np.asarray(v["y"], np.float64),
                     np.asarray(v["z"], np.float64)], axis=1)


# --------------------------------------------------------------------------- DTU protocol


def _mean_below(d: np.ndarray, max_dist: float, default: float = float("nan")) -> float:
    """Mean of the (N,) distances below ``max_dist`` (docs/method.md 8.1); ``default`` if none
    is."""
    d = d[d < max_dist]
    return float(d.mean()) if len(d) else default


def obs_mask_filter(points: np.ndarray, obs: ObsMask, patch: float = 60.0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Masks of points inside the DTU bounding box (data_in) and observed (data_in_obs).

    docs/method.md 8.1: inbound is BB_min - patch <= p < BB_max + 2 * patch on all three axes; the
    voxel index is round((p - BB_min) / Res) (round half to even, as numpy's ``around``); a point is
    observed when that index lies in the grid and ObsMask is true there.

    Args:
        points: (N, 3) float points in mm.
        obs: the scan's `ObsMask`.
        patch: margin in mm (60).

    Returns:
        in_bb: (N,) bool; in_obs: (N,) bool (a subset of in_bb).
    """
    points = _check_points("points", points)
    lo = obs.bb[0] - np.float32(patch)  # float32 arithmetic, as the reference
    hi = obs.bb[1] + np.float32(patch * 2)
    in_bb = np.all((points >= lo) & (points < hi), axis=1)
    idx = np.around((points[in_bb] - obs.bb[0]) / obs.res).astype(np.int64)
    shape = np.asarray(obs.mask.shape)
    in_grid = np.all((idx >= 0) & (idx < shape), axis=1)
    g = idx[in_grid]
    observed = np.zeros(len(idx), dtype=bool)
    observed[np.flatnonzero(in_grid)] = obs.mask[g[:, 0], g[:, 1], g[:, 2]]
    in_obs = np.zeros(len(points), dtype=bool)
    in_obs[np.flatnonzero(in_bb)] = observed
    return in_bb, in_obs


def dtu_chamfer_arrays(points: np.ndarray, stl: np.ndarray, obs: ObsMask, plane: np.ndarray, *,
                       mode: str = "pcd", faces: np.ndarray | None = None, seed: int | None = 0,
                       downsample_density: float = 0.2, patch_size: float = 60.0,
                       max_dist: float = 20.0, fscore_threshold: float | None = None) -> dict:
    """The DTU protocol (docs/method.md 8.1) on arrays already in memory.

    Args:
        points: (N, 3) float prediction in DTU world mm (point cloud, or mesh vertices).
        stl: (M, 3) float ground-truth structured-light points.
        obs: the scan's `ObsMask`.
        plane: (4,) ground plane; completeness uses the STL points with plane . [x; 1] > 0.
        mode: ``"pcd"`` or ``"mesh"`` (then ``faces`` is required and the mesh is scored by its
            surface, `mesh_surface_points` at ``downsample_density`` on the reference's grids,
            ``oversample=1``).
        faces: (F, 3) int triangles for mesh mode.
        seed: seed of the random shuffle before downsampling (None: unseeded, as the reference).
        downsample_density: greedy downsampling radius and mesh sampling spacing (0.2 mm).
        patch_size: bounding-box margin (60 mm; the upper margin is twice it).
        max_dist: distances at or above it are left out of both means (20 mm).
        fscore_threshold: if given, also ``precision`` (observed prediction points within it of
            the STL), ``recall`` (STL points above the plane within it of data_in) and
            ``fscore``, counting all points (not part of the DTU protocol).

    Returns:
        dict with float ``accuracy`` (prediction -> STL), ``completeness`` (STL above the plane ->
        prediction) and ``overall`` (their mean), in mm; NaN when a side has no points.
    """
    t0 = time.perf_counter()
    points = _check_points("points", points)
    stl = _check_points("stl", stl)
    plane = np.asarray(plane, dtype=np.float64).reshape(-1)
    if plane.shape != (4,):
        raise InputError(f"plane: expected 4 coefficients, got {plane.size}")
    if mode == "mesh":
        if faces is None:
            raise InputError("DTU mesh mode needs faces (an (F, 3) int array)")
        # the same steps as a cloud's below, on the sampled surface, as the reference samples
        data = mesh_surface_points(points, faces, downsample_density, seed, oversample=1)
    elif mode == "pcd":
        data = shuffle_rows(points, seed)
        data = data[greedy_radius_downsample(data, downsample_density)]
    else:
        raise InputError(f"mode must be 'pcd' or 'mesh', got {mode!r}")
    t1 = time.perf_counter()
    in_bb, in_obs = obs_mask_filter(data, obs, patch_size)
    data_in, data_in_obs = data[in_bb], data[in_obs]
    ub = max(max_dist, fscore_threshold or 0.0)
    d2s = nn_distances(data_in_obs, stl, upper_bound=ub)
    above = stl @ plane[:3] + plane[3] > 0
    s2d = nn_distances(stl[above], data_in, upper_bound=ub)
    acc = _mean_below(d2s, max_dist)
    comp = _mean_below(s2d, max_dist)
    out = {"accuracy": acc, "completeness": comp, "overall": (acc + comp) / 2}
    if fscore_threshold is not None:
        prec = float((d2s < fscore_threshold).mean()) if len(d2s) else float("nan")
        rec = float((s2d < fscore_threshold).mean()) if len(s2d) else float("nan")
        out.update(precision=prec, recall=rec,
                   fscore=2 * prec * rec / (prec + rec) if prec + rec > 0 else 0.0)
    log.debug("DTU chamfer: %d -> %d points after downsampling (%.1fs), %d in BB, %d observed, "
              "%d STL above plane; total %.1fs", len(points), len(data), t1 - t0, len(data_in),
              len(data_in_obs), int(above.sum()), time.perf_counter() - t0)
    return out


def dtu_chamfer(points: np.ndarray, dtu_dir: str | Path, scan: int, mode: str = "pcd",
                faces: np.ndarray | None = None, **kwargs) -> dict:
    """DTU Chamfer of a prediction against scan ``scan``'s ground truth (docs/method.md 8.1).

    Reads ``ObsMask/ObsMask{scan}_10.mat``, ``ObsMask/Plane{scan}.mat`` (scan 82: Plane83) and
    ``Points/stl/stl{scan:03d}_total.ply`` under ``dtu_dir`` (or ``dtu_dir/DTU_MVS_Data``).

    Args:
        points: (N, 3) float prediction in DTU world mm (mesh vertices in mesh mode).
        dtu_dir: the DTU ground-truth root.
        scan: DTU scan number.
        mode: ``"pcd"`` or ``"mesh"``.
        faces: (F, 3) int triangles (mesh mode).
        **kwargs: `dtu_chamfer_arrays` options (seed, downsample_density, patch_size, max_dist).

    Returns:
        dict(accuracy, completeness, overall) in mm.

    Raises:
        InputError naming a missing or unreadable file.
    """
    files = find_dtu_files(dtu_dir, scan)
    obs = load_obs_mask(files.obs_mask)
    plane = load_plane(files.plane)
    stl = checked_ground_truth(_read_ply_points(files.stl), files.stl)
    return dtu_chamfer_arrays(points, stl, obs, plane, mode=mode, faces=faces, **kwargs)


# --------------------------------------------------------------------------- generic


def chamfer_fscore(pred: np.ndarray, gt: np.ndarray, threshold: float,
                   max_dist: float | None = None, downsample: float | None = None,
                   seed: int | None = 0) -> dict:
    """Two-way Chamfer distance and F-score between any two point clouds.

    accuracy = mean_p min_g |p - g|, completeness = mean_g min_p |g - p| (each over distances
    below ``max_dist`` when given, as docs/method.md 8.1/8.2), overall = their mean;
    precision = fraction of prediction points within ``threshold`` of the ground truth, recall =
    fraction of ground-truth points within ``threshold`` of the prediction (all points count),
    fscore = 2 P R / (P + R) (Knapitsch et al., Tanks and Temples).

    Args:
        pred: (N, 3) float predicted points.
        gt: (M, 3) float ground-truth points.
        threshold: F-score distance threshold, in the clouds' units.
        max_dist: optional cut-off for the Chamfer means.
        downsample: optional radius; both clouds are shuffled (``seed``) and greedily downsampled
            at it first (`greedy_radius_downsample`), which evens out uneven densities.
        seed: shuffle seed for ``downsample``.

    Returns:
        dict of floats: accuracy, completeness, overall, precision, recall, fscore.
    """
    pred = _check_points("pred", pred)
    gt = _check_points("gt", gt)
    if len(pred) == 0 or len(gt) == 0:
        raise InputError(f"Chamfer needs points on both sides; got {len(pred)} predicted and "
                         f"{len(gt)} ground-truth points")
    if not threshold > 0:
        raise InputError(f"F-score threshold must be > 0, got {threshold}")
    if downsample:
        rng = np.random.default_rng(seed)
        pred, gt = pred[rng.permutation(len(pred))], gt[rng.permutation(len(gt))]
        pred = pred[greedy_radius_downsample(pred, downsample)]
        gt = gt[greedy_radius_downsample(gt, downsample)]
    d_pg = nn_distances(pred, gt)
    d_gp = nn_distances(gt, pred)
    if max_dist is None:
        acc, comp = float(d_pg.mean()), float(d_gp.mean())
    else:
        acc, comp = _mean_below(d_pg, max_dist), _mean_below(d_gp, max_dist)
    precision = float((d_pg < threshold).mean())
    recall = float((d_gp < threshold).mean())
    f = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {"accuracy": acc, "completeness": comp, "overall": (acc + comp) / 2,
            "precision": precision, "recall": recall, "fscore": f}
