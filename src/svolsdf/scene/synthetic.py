"""Synthetic scenes with exact ground truth: procedural textured objects on a textured table.

`make_synthetic_scene` ray-casts an analytic signed distance function (a smooth union of spheres,
rounded boxes, tori and capsules, randomized by a seed) standing on a finite table plane, seen by
cameras on a DTU-like spherical cap, and writes the IDR / VolSDF layout (docs/method.md 1.1)::

    OUT/image/000000.png ...   RGB 8-bit renders (2x2 supersampled by default)
    OUT/mask/000.png ...       object mask, 8-bit greyscale: 255 object, 0 table or background
    OUT/cameras.npz            world_mat_i = K [R | t] (4x4), scale_mat_i (unit -> world),
                               camera_mat_i = K (4x4), and the inverses of all three
    OUT/pair.txt               MVSNet pair file (sources ranked by MVSNet's view-angle score)
    OUT/gt_depth/000.npy ...   float32 (H, W) z-depth in world units at pixel centres, table
                               included; 0 where the ray hits nothing (background)
    OUT/gt_points.ply          samples of the OBJECT surface above the table, world units
    OUT/gt_points_visibility.npy  uint8 (N,) number of views that see each gt point
    OUT/gt_mesh.ply            the object surface as a triangle mesh (marching cubes, world units)
    OUT/scene.json             the generator's config, objects, table, light, cameras' summary

World frame and units (DTU-like): millimetres; z is up, the table is the plane z = 0 (a square of
side ``table_size``), the object stands on it centred on the z axis, about 100-200 mm across; the
cameras look at the object's centre from ``distance`` (~600 mm) on a cap spanning ``azimuth_span``
degrees around the -y direction and elevations ``elevation`` degrees above the table, in rows like
DTU's. Intrinsics follow DTU's relative focal length (f ~ 1.8 x image width) with a slightly
off-centre principal point. Camera axes are OpenCV's (scene/cameras.py).

Normalization (docs/method.md 1.2, VolSDF convention): scale_mat =
[[s,0,0,cx],[0,s,0,cy],[0,0,s,cz], [0,0,0,1]] with c the object's bounding-sphere centre (where all
optical axes meet) and s = max(1.1 * (max camera distance to c) / 3, 1.05 * object radius): the
object lies inside the unit sphere and the cameras within radius ~2.7 (VolSDF's radius-3 region of
interest).

Shading is Lambertian with an ambient term, a fixed directional light and soft shadows, so the
images are consistent across views (no view-dependent effects) unless ``specular`` adds a
Blinn-Phong highlight to the object; the textures are solid (3D)
procedural patterns (multi-octave value noise, stripes, checkers) so that multi-view stereo has
texture to match everywhere. Output is byte-for-byte deterministic for a seed (every file,
including the zip inside ``cameras.npz``).

Borrowed cameras: ``cameras_from`` (an IDR scene folder with ``cameras.npz`` or
``cameras_sphere.npz`` and ``image/`` or ``images/``) renders the object with that scene's cameras
(resized to ``width`` x ``height``), placed at its scale_mat centre, scaled to its unit sphere, on a
table orthogonal to the cameras' mean "up" direction, in its world units.

The objects and their textures are built in `svolsdf.scene.synthetic_shapes` and ray-cast in
`svolsdf.scene.synthetic_render`; this module places the cameras, computes the ground truth,
writes the files, and re-exports those modules' public names.
"""

from __future__ import annotations

import io
import json
import logging
import math
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from svolsdf.errors import InputError
from svolsdf.io.paths import input_dir, user_path
from svolsdf.io.ply import atomic_path, write_mesh_ply, write_points_ply
from svolsdf.io.replace import OutputSpec, check_replace, replace_outputs
from svolsdf.scene.cameras import Cameras, decompose_projection
from svolsdf.scene.size import parse_size  # re-exported: the one size parser
from svolsdf.scene.synthetic_render import _World, render_view
from svolsdf.scene.synthetic_shapes import OBJECT_KINDS, SynthObject, _sdf_grad, make_object

__all__ = [
    "OBJECT_KINDS",
    "SCENE_OUTPUT",
    "SynthConfig",
    "SynthObject",
    "made_with",
    "make_object",
    "make_synthetic_scene",
    "parse_size",
    "render_view",
]

log = logging.getLogger(__name__)

GENERATOR = "svolsdf.synth"
_SCENE_FILES = ("cameras.npz", "pair.txt", "gt_points.ply", "gt_points_visibility.npy",
                "gt_mesh.ply", "scene.json")
_SCENE_DIRS = ("image", "mask", "gt_depth")


@dataclass
class SynthConfig:
    """Configuration of a synthetic scene (``svolsdf synth``)."""

    seed: int = 0
    """Random seed: the object, its textures and the camera jitter. Same seed, same bytes."""
    views: int = 9
    """Number of views on the cap (the default 9 leaves room for 3 inputs and held-out views)."""
    width: int = 768
    """Image width in pixels."""
    height: int = 576
    """Image height in pixels."""
    object: str = "random"
    """Object kind: random, sphere, box, torus, capsule or blobs (`OBJECT_KINDS`)."""
    supersample: int = 2
    """Anti-aliasing samples per pixel axis for the images (1 = one ray through each pixel
    centre). Depth and masks always come from the pixel-centre ray."""
    distance: float = 600.0
    """Mean camera distance to the object centre, world units (DTU: 500-800 mm)."""
    distance_jitter: float = 0.05
    """Relative random variation of each camera's distance."""
    elevation: tuple[float, float] = (25.0, 60.0)
    """Lowest and highest camera elevation above the table, degrees (DTU spans about 45)."""
    azimuth_span: float = 80.0
    """Horizontal angle spanned by a row of cameras, degrees."""
    focal: float = 1.8
    """Focal length as a multiple of the image width (DTU: 2890 px at 1600 px wide)."""
    intrinsics_jitter: float = 1.0
    """Scale of the per-view random variation of the intrinsics (focal length +-1 %, principal
    point +-2 % of the image size, as a rig of different cameras); 0 gives every view the same
    camera with the principal point at the image centre, as photos from one camera."""
    table_size: float = 800.0
    """Side of the square table, world units."""
    light_dir: tuple[float, float, float] = (-0.35, -0.55, 0.76)
    """Direction towards the directional light (normalized on use), world frame."""
    ambient: float = 0.3
    """Ambient light fraction; the rest is Lambertian."""
    soft_shadows: bool = True
    """Cast soft shadows of the object (on the table and on itself)."""
    gt_points: int = 200_000
    """Number of object-surface samples drawn for gt_points.ply (before dropping those on or
    under the table)."""
    mesh_resolution: float = 1.5
    """Marching-cubes cell size for gt_mesh.ply and the surface sampling, world units."""
    chunk: int = 1 << 17
    """Rays per rendering chunk (memory bound)."""
    cameras_from: str | None = None
    """Borrow the cameras of this IDR scene folder instead of the synthetic cap."""
    camera_views: list[int] | None = None
    """With ``cameras_from``: which of its views to use (default: ``views`` evenly spaced ids)."""
    texture_contrast: float = 1.0
    """Contrast of the object's texture: 1 the full procedural pattern, lower values a
    low-texture object (colours pulled towards each primitive's mean colour)."""
    specular: float = 0.0
    """Strength of a white Blinn-Phong highlight on the object (0: Lambertian, the default): a
    view-dependent colour that multi-view photo-consistency does not model, as on DTU's metal
    and glazed objects; with a low ``texture_contrast`` a texture-poor, specular object."""
    shininess: float = 40.0
    """Blinn-Phong exponent of that highlight (larger: smaller, sharper highlights)."""

    def __post_init__(self) -> None:
        if self.object not in OBJECT_KINDS:
            raise InputError(
                f"unknown object kind {self.object!r}; choose one of {', '.join(OBJECT_KINDS)}"
            )
        if self.views < 1:
            raise InputError(f"--views must be at least 1, got {self.views}")
        if self.seed < 0:  # numpy's generators take non-negative seeds only
            raise InputError(f"--seed must be a non-negative integer, got {self.seed}")
        from svolsdf.scene.checks import MIN_SIDE

        if self.width < MIN_SIDE or self.height < MIN_SIDE:  # below, no run can use the scene
            raise InputError(f"image size must be at least {MIN_SIDE}x{MIN_SIDE} (the smallest "
                             f"that svolsdf reconstruct takes), got {self.width}x{self.height}")
        if not 0.0 <= self.texture_contrast <= 1.0:
            raise InputError(f"--texture-contrast must be in [0, 1], got {self.texture_contrast}")
        if not 0.0 <= self.specular <= 1.0:
            raise InputError(f"--specular must be in [0, 1], got {self.specular}")
        if self.shininess <= 0:
            raise InputError(f"--shininess must be positive, got {self.shininess}")
        if self.supersample < 1:
            raise InputError(f"supersample must be >= 1, got {self.supersample}")


# =============================================================================== cameras
def _look_at(pos: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera (4, 4), OpenCV axes, camera at ``pos`` looking at ``target``."""
    f = target - pos
    f = f / np.linalg.norm(f)
    x = np.cross(f, up)
    x = x / np.linalg.norm(x)
    y = np.cross(f, x)
    R = np.stack([x, y, f])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ pos
    return w2c


def _cap_layout(n: int) -> list[int]:
    """Cameras per row (bottom to top), DTU-like rows."""
    rows = max(1, round(math.sqrt(n)))
    base, extra = divmod(n, rows)
    return [base + (1 if r < extra else 0) for r in range(rows)]


def _cap_cameras(cfg: SynthConfig, target: np.ndarray, rng: np.random.Generator) -> Cameras:
    W, H = cfg.width, cfg.height
    Ks, w2cs = [], []
    rows = _cap_layout(cfg.views)
    e_lo, e_hi = cfg.elevation
    for r, count in enumerate(rows):
        el = math.radians((e_lo + e_hi) / 2 if len(rows) == 1
                          else e_lo + (e_hi - e_lo) * r / (len(rows) - 1))
        for j in range(count):
            frac = 0.5 if count == 1 else j / (count - 1)
            # rows are offset like DTU's staggered rings
            span = cfg.azimuth_span * (1.0 - 0.25 * r / max(1, len(rows) - 1))
            az = math.radians(-span / 2 + span * frac)
            dist = cfg.distance * (1.0 + cfg.distance_jitter * rng.uniform(-1, 1))
            direction = np.array([math.cos(el) * math.sin(az), -math.cos(el) * math.cos(az),
                                  math.sin(el)])
            aim = target + rng.uniform(-3.0, 3.0, size=3)
            w2cs.append(_look_at(target + dist * direction, aim, np.array([0.0, 0.0, 1.0])))
            jit = cfg.intrinsics_jitter  # the draws happen at any jitter: same stream
            f = cfg.focal * W * (1.0 + jit * rng.uniform(-0.01, 0.01))
            K = np.array([[f, 0, (W - 1) / 2 + jit * rng.uniform(-0.02, 0.02) * W],
                          [0, f, (H - 1) / 2 + jit * rng.uniform(-0.02, 0.02) * H],
                          [0, 0, 1.0]])
            Ks.append(K)
    return Cameras(torch.tensor(np.stack(Ks)), torch.tensor(np.stack(w2cs)), W, H)


def _borrowed_cameras(cfg: SynthConfig) -> tuple[Cameras, list[int], np.ndarray]:
    """Cameras of an IDR scene, resized; returns (cameras, view ids, scale_mat (4, 4))."""
    root = input_dir(cfg.cameras_from, "IDR scene folder", "--cameras-from")
    npz = next((root / n for n in ("cameras.npz", "cameras_sphere.npz") if (root / n).is_file()),
               None)
    if npz is None:
        raise InputError(f"{root}: no cameras.npz or cameras_sphere.npz to borrow cameras from")
    img_dir = next((root / n for n in ("image", "images") if (root / n).is_dir()), None)
    if img_dir is None:
        raise InputError(f"{root}: no image/ or images/ folder (needed for the original size)")
    files = sorted(p for p in img_dir.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not files:
        raise InputError(f"{img_dir}: no images")
    try:
        with Image.open(files[0]) as im:
            W0, H0 = im.size
    except OSError as e:
        raise InputError(f"{files[0]}: unreadable image ({e})") from None
    data = np.load(npz)
    n = sum(1 for k in data.files if k.startswith("world_mat_") and "inv" not in k)
    ids = list(cfg.camera_views) if cfg.camera_views else sorted(
        {int(round(x)) for x in np.linspace(0, n - 1, cfg.views)})
    Ks, w2cs = [], []
    for i in ids:
        if f"world_mat_{i}" not in data.files:
            raise InputError(f"{npz}: view id {i} does not exist (it has {n} cameras)")
        try:
            K, w2c = decompose_projection(torch.tensor(data[f"world_mat_{i}"], dtype=torch.float64))
        except ValueError as e:
            raise InputError(f"{npz}: world_mat_{i}: {e}") from None
        Ks.append(K)
        w2cs.append(w2c)
    cams = Cameras(torch.stack(Ks), torch.stack(w2cs), W0, H0).resize(cfg.width, cfg.height)
    scale_mat = np.asarray(data[f"scale_mat_{ids[0]}"], dtype=np.float64)
    return cams, ids, scale_mat


# =============================================================================== ground truth
def _object_mesh(obj: SynthObject, res: float, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the object SDF (local frame). Returns verts (V, 3), faces (F, 3)."""
    from skimage.measure import marching_cubes

    c, r = obj.bound()
    lo = c - r - 2 * res
    n = int(math.ceil((2 * r + 4 * res) / res)) + 1
    ax = [torch.arange(n, dtype=torch.float64) * res + lo[k] for k in range(3)]
    gx, gy, gz = torch.meshgrid(*ax, indexing="ij")
    pts = torch.stack([gx.reshape(-1), gy.reshape(-1), gz.reshape(-1)], -1).to(torch.float32)
    vals = torch.cat([obj.sdf(pts[s:s + chunk]) for s in range(0, len(pts), chunk)])
    vol = vals.reshape(n, n, n).numpy()
    verts, faces, _, _ = marching_cubes(vol, level=0.0, spacing=(res, res, res))
    return verts + lo, faces.astype(np.int64)


def _project_to_surface(obj: SynthObject, p: Tensor, iters: int = 4) -> Tensor:
    """Newton-project points onto the SDF zero set: p <- p - f grad f / |grad f|^2."""
    p = p.to(torch.float64)
    for _ in range(iters):
        g = _sdf_grad(obj, p, 1e-3)
        f = obj.sdf(p)
        p = p - (f / (g * g).sum(-1).clamp(min=1e-12))[:, None] * g
    return p


def _sample_surface(obj: SynthObject, verts: np.ndarray, faces: np.ndarray, n: int,
                    rng: np.random.Generator, chunk: int) -> np.ndarray:
    """Area-uniform samples on the object surface above the table (local frame), (M, 3)."""
    tri = verts[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    fi = rng.choice(len(faces), size=n, p=area / area.sum())
    a, b = rng.random(n), rng.random(n)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    t = tri[fi]
    pts = t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])
    p = torch.tensor(pts)
    out = torch.cat([_project_to_surface(obj, p[s:s + chunk]) for s in range(0, n, chunk)])
    res = obj.sdf(out.to(torch.float32)).abs()
    keep = (out[:, 2] > 0.05) & (res < 1e-2)
    return out[keep].numpy()


def _visibility(points: np.ndarray, cams: Cameras, depths: list[np.ndarray]) -> np.ndarray:
    """(V, N) bool: point in front of the rendered surface (within a few pixel footprints)."""
    uv, z = cams.project(torch.tensor(points, dtype=torch.float64))
    out = np.zeros((len(cams), len(points)), bool)
    for v in range(len(cams)):
        u = torch.round(uv[v, :, 0]).long()
        w = torch.round(uv[v, :, 1]).long()
        inside = (u >= 0) & (u < cams.width) & (w >= 0) & (w < cams.height) & (z[v] > 0)
        dm = torch.from_numpy(depths[v]).to(torch.float64)
        d = torch.zeros_like(z[v])
        d[inside] = dm[w[inside], u[inside]]
        fx = float(cams.K[v, 0, 0])
        tol = 3.0 * z[v] / fx + 0.002 * z[v]
        out[v] = (inside & (d > 0) & ((z[v] - d).abs() < tol)).numpy()
    return out


def _pairs(points: np.ndarray, vis: np.ndarray, cams: Cameras, rng: np.random.Generator,
           max_src: int = 10) -> list[list[tuple[int, float]]]:
    """MVSNet view selection score: sum over points seen by both views of a Gaussian of the
    triangulation angle (theta0 = 5 deg, sigma = 1 below / 10 above; MVSNet colmap2mvsnet)."""
    sel = rng.choice(len(points), size=min(len(points), 4000), replace=False)
    pts, vis = points[np.sort(sel)], vis[:, np.sort(sel)]
    centres = cams.centers.numpy()
    V = len(cams)
    out = []
    for i in range(V):
        scores = []
        for j in range(V):
            if j == i:
                continue
            both = vis[i] & vis[j]
            a = centres[i] - pts[both]
            b = centres[j] - pts[both]
            cosang = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
            theta = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
            sig = np.where(theta <= 5.0, 1.0, 10.0)
            scores.append((j, float(np.exp(-((theta - 5.0) ** 2) / (2 * sig**2)).sum())))
        scores.sort(key=lambda x: (-x[1], x[0]))
        out.append(scores[:max_src])
    return out


# =============================================================================== writing
def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """np.savez-compatible archive with fixed zip timestamps (byte-deterministic)."""
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as zf:
        for k in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asarray(arrays[k]), allow_pickle=False)
            zf.writestr(zipfile.ZipInfo(k + ".npy", date_time=(1980, 1, 1, 0, 0, 0)),
                        buf.getvalue())


def _write_png(path: Path, arr: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        Image.fromarray(arr).save(tmp, format="PNG")


def _write_npy(path: Path, arr: np.ndarray) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, arr)


def _write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def _earlier_scene(out: Path) -> dict[str, int | None] | None:
    """The files a synthetic scene written before `svolsdf.io.replace` kept its record holds,
    from its scene.json; None when ``out`` is no synthetic scene."""
    try:
        meta = json.loads((out / "scene.json").read_text())
        views = int(meta["views"]) if meta.get("generator") == GENERATOR else None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if views is None:
        return None
    files: dict[str, int | None] = dict.fromkeys(_SCENE_FILES)
    for i in range(views):
        files.update(dict.fromkeys((f"image/{i:06d}.png", f"mask/{i:03d}.png",
                                    f"gt_depth/{i:03d}.npy")))
    return files


SCENE_OUTPUT = OutputSpec(command="svolsdf synth", names=frozenset(_SCENE_FILES + _SCENE_DIRS),
                          earlier="a synthetic scene", legacy=_earlier_scene, option=None)
"""What `make_synthetic_scene` writes (`svolsdf.io.replace`): a rerun replaces only that."""


def made_with(folder: str | Path, cfg: SynthConfig) -> bool:
    """True when ``folder`` holds the synthetic scene that ``cfg`` makes (its scene.json says
    so), False for another one (a size, seed, ... of its own) or none."""
    try:
        meta = json.loads((Path(folder) / "scene.json").read_text())
    except (OSError, ValueError):
        return False
    want = json.loads(json.dumps(_json_ready(asdict(cfg))))
    have = meta.get("config") if isinstance(meta, dict) else None
    if isinstance(have, dict):  # a scene.json without the highlight's options: a Lambertian one
        have = {**_LAMBERTIAN, **have}
    return isinstance(meta, dict) and meta.get("generator") == GENERATOR and have == want


#: what a scene.json written without ``specular`` and ``shininess`` (`_config_record`) means
_LAMBERTIAN = {"specular": 0.0, "shininess": 40.0}


def _config_record(cfg: SynthConfig) -> dict:
    """``cfg`` as scene.json records it: a Lambertian scene (``specular`` 0) without the
    highlight's options, as scenes were written before they existed (so those still match)."""
    d = asdict(cfg)
    if not cfg.specular and cfg.shininess == _LAMBERTIAN["shininess"]:
        d.pop("specular"), d.pop("shininess")
    return d


def _json_ready(x):
    if isinstance(x, dict):
        return {k: _json_ready(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_ready(v) for v in x]
    if isinstance(x, (np.ndarray, Tensor)):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def make_synthetic_scene(out_dir, cfg: SynthConfig | None = None) -> Path:
    """Render a synthetic scene with ground truth and write it in the IDR layout (module docstring).

    Args:
        out_dir: output folder; created if missing. It must be empty or an earlier synthetic
            scene, whose files are replaced only once the new scene is complete; a file the
            user put among them is never removed (`svolsdf.io.replace`).
        cfg: generator settings (default `SynthConfig()`: 9 views at 768x576, random object).

    Returns:
        ``out_dir`` as a Path.

    Raises:
        InputError: ``out_dir`` is a file, a non-empty foreign folder, or holds a file of the
            user's where the scene is written; bad ``cameras_from``. Raised before any
            rendering and before ``out_dir`` is touched.
    """
    cfg = cfg or SynthConfig()
    inputs = [cfg.cameras_from]
    out = check_replace(user_path(out_dir), SCENE_OUTPUT, inputs)
    borrowed = _borrowed_cameras(cfg) if cfg.cameras_from else None
    with replace_outputs(out, SCENE_OUTPUT, inputs) as stage:
        views, points = _render_scene(stage, cfg, borrowed)
    log.info("synthetic scene: %d views %dx%d, %d gt points -> %s", views, cfg.width,
             cfg.height, points, out)
    return out


def _render_scene(out: Path, cfg: SynthConfig, borrowed: tuple | None) -> tuple[int, int]:
    """Render the scene into ``out`` (an empty folder); returns (views, ground-truth points)."""
    from tqdm import tqdm

    rng = np.random.default_rng([cfg.seed, 2])

    obj = make_object(cfg.object, cfg.seed)
    obj.contrast = float(cfg.texture_contrast)
    # Stand the object on the table: lowest point 3 mm under z = 0, centred on the z axis.
    verts, faces = _object_mesh(obj, max(cfg.mesh_resolution, 4.0), cfg.chunk)
    lo, hi = verts.min(0), verts.max(0)
    obj.translate(np.array([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -3.0 - lo[2]]))
    verts, faces = _object_mesh(obj, cfg.mesh_resolution, cfg.chunk)
    lo, hi = verts.min(0), verts.max(0)
    vis_lo = np.array([lo[0], lo[1], max(lo[2], 0.0)])
    centre_loc = (vis_lo + hi) / 2
    radius_loc = float(np.linalg.norm(verts[verts[:, 2] > 0] - centre_loc, axis=1).max())

    light = torch.tensor(cfg.light_dir, dtype=torch.float64)
    light = light / light.norm()
    if cfg.cameras_from:
        cams, view_ids, borrowed_scale = borrowed
        c_world = torch.tensor(borrowed_scale[:3, 3])
        s_world = float(borrowed_scale[0, 0])
        up = -cams.w2c[:, 1, :3].mean(0)
        up = up / up.norm()
        xa = cams.w2c[:, 0, :3].mean(0)
        xa = xa - (xa @ up) * up
        xa = xa / xa.norm()
        rot = torch.stack([xa, torch.linalg.cross(up, xa), up], 1)
        scale = 0.6 * s_world / radius_loc  # the object fills ~60% of the unit sphere
        origin = c_world - scale * (rot @ torch.tensor(centre_loc))
    else:
        view_ids = list(range(cfg.views))
        rot = torch.eye(4, dtype=torch.float64)[:3, :3]
        origin = torch.zeros(3, dtype=torch.float64)
        scale = 1.0
        cams = _cap_cameras(cfg, centre_loc, rng)
    world = _World(obj=obj, table_half=cfg.table_size / 2,
                   light=(rot.T @ light).to(torch.float32),  # the light is given in world axes
                   ambient=cfg.ambient, soft_shadows=cfg.soft_shadows, table_seed=obj.seed + 1000,
                   rot=rot, origin=origin, scale=scale, specular=cfg.specular,
                   shininess=cfg.shininess)
    centre_w = world.to_world(torch.tensor(centre_loc)[None])[0].numpy()
    radius_w = radius_loc * scale

    # Normalization, docs/method.md 1.2 (VolSDF): s = 1.1 * max camera distance / 3, but never so
    # small that the object leaves the unit sphere.
    if cfg.cameras_from:
        scale_mat = borrowed_scale
    else:
        max_dist = float(np.linalg.norm(cams.centers.numpy() - centre_w, axis=1).max())
        s = max(1.1 * max_dist / 3.0, 1.05 * radius_w)
        scale_mat = np.eye(4)
        scale_mat[:3, :3] *= s
        scale_mat[:3, 3] = centre_w

    for d in _SCENE_DIRS:
        (out / d).mkdir()
    depths = []
    npz: dict[str, np.ndarray] = {}
    for i in tqdm(range(len(cams)), desc="synth: rendering", unit="view", disable=None):
        img, depth, mask = render_view(world, cams[i], cfg.supersample, cfg.chunk)
        _write_png(out / "image" / f"{i:06d}.png", img)
        _write_png(out / "mask" / f"{i:03d}.png", (mask * 255).astype(np.uint8))
        _write_npy(out / "gt_depth" / f"{i:03d}.npy", depth)
        depths.append(depth)
        K4 = np.eye(4)
        K4[:3, :3] = cams.K[i].numpy()
        P = K4 @ cams.w2c[i].numpy()
        for name, m in (("world_mat", P), ("scale_mat", scale_mat), ("camera_mat", K4)):
            npz[f"{name}_{i}"] = m
            npz[f"{name}_inv_{i}"] = np.linalg.inv(m)
    _write_npz(out / "cameras.npz", npz)

    # Ground-truth surface: marching cubes, area-uniform samples Newton-projected onto the SDF.
    pts_loc = _sample_surface(obj, verts, faces, cfg.gt_points, rng, cfg.chunk)
    pts_w = world.to_world(torch.tensor(pts_loc)).numpy()
    cols = obj.albedo(torch.tensor(pts_loc, dtype=torch.float32)).numpy()
    write_points_ply(out / "gt_points.ply", pts_w, cols)
    vis = _visibility(pts_w, cams, depths)
    _write_npy(out / "gt_points_visibility.npy", vis.sum(0).astype(np.uint8))
    keepf = verts[faces].mean(1)[:, 2] > 0
    write_mesh_ply(out / "gt_mesh.ply", world.to_world(torch.tensor(verts)).numpy(),
                   faces[keepf])

    pairs = _pairs(pts_w, vis, cams, rng)
    lines = [str(len(cams))]
    for i, src in enumerate(pairs):
        lines.append(str(i))
        lines.append(" ".join([str(len(src))] + [f"{j} {sc:.2f}" for j, sc in src]))
    _write_text(out / "pair.txt", "\n".join(lines) + "\n")

    meta = {
        "generator": GENERATOR,
        "format": "idr",
        "units": "mm" if not cfg.cameras_from else "as in cameras_from",
        "config": _config_record(cfg),
        "views": len(cams),
        "view_ids_source": view_ids,
        "width": cfg.width,
        "height": cfg.height,
        "depth": "float32 z-depth at pixel centres in world units; 0 = no surface; table included",
        "mask": "255 = object (first hit at the pixel centre), 0 = table or background",
        "object": {"kind": cfg.object, "blend": obj.blend, "primitives": obj.primitives,
                   "bounding_sphere_world": {"center": centre_w, "radius": radius_w}},
        "local_to_world": {"rotation": world.rot, "origin": world.origin, "scale": world.scale,
                           "note": "object and table are defined in a local frame (z up, table "
                                   "z = 0); world = scale * rotation @ local + origin"},
        "table": {"plane_world": {"normal": world.rot[:, 2], "point": world.origin},
                  "size": cfg.table_size * scale},
        "light_dir_world": light.tolist(),
        "gt_points": int(len(pts_w)),
        "scale_mat": scale_mat,
        "camera_centers": cams.centers.numpy(),
        "depth_range": [[float(d[d > 0].min()) if (d > 0).any() else 0.0, float(d.max())]
                        for d in depths],
    }
    _write_text(out / "scene.json", json.dumps(_json_ready(meta), indent=1, sort_keys=True) + "\n")
    return len(cams), len(pts_w)
