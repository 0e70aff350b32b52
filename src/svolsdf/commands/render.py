"""Novel views of a finished run: volume rendering and image-based rendering (docs/method.md 7).

``svolsdf render OUT`` renders, for each target camera,

- the field's volume-rendered colour, z-depth and normals (``Run.render_views``, the
  eval-mode sampler) -> ``OUT/renders/<id>.png``, ``OUT/renders/depth/<id>.png`` (colour-coded
  preview) and ``<id>.npy`` (world z-depth, 0 where the opacity is below 0.5),
  ``OUT/renders/normals/<id>.png`` (camera-frame normals, OpenCV axes, (n + 1) / 2 times the
  opacity);
- with ``ibr=True``, the image-based rendering of docs/method.md 7 (`svolsdf.ibr.ibr_render`): the
  input images warped by the rendered target depth and the rendered input-view depths, blended
  with the rendered colour as the fallback -> ``OUT/renders_ibr/<id>.png``.

Targets are scene views (by id: the held-out test views of ``views.json`` by default, else the
inputs) or an orbit through the input views (`svolsdf.ibr.orbit_cameras`), written as frames
``OUT/renders/orbit/NNN.png`` plus ``OUT/renders/orbit.mp4`` (or ``orbit.gif`` when no ffmpeg
backend is installed).

The RGB is written as rendered: docs/method.md 8 composites onto white only inside the metrics, with
the ground-truth masks, so nothing is composited here.

Depth ranges of the target rays (unit frame): a scene view uses its own depth range from the
scene (x 0.9 / x 1.1, as the guide-depth stage does for the inputs); an orbit camera uses the
z-range of the field's bounding box corners (or the union of the input views' ranges for a field
without a box); ``render_views`` further clips every ray to the field's bounding sphere.

A depth pixel is "surface" when the rendered opacity sum_i w_i >= ``OPACITY_SURFACE`` (0.5); the
IBR treats other pixels as having no depth, so the rendered colour is used there (docs/method.md 7
step 4, "holes").
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from svolsdf.errors import InputError, raise_if_interrupted
from svolsdf.scene.cameras import Cameras

__all__ = [
    "OPACITY_SURFACE",
    "box_near_far",
    "camera_normals",
    "mesh_depth_fill",
    "open_run",
    "render_outputs",
    "write_video",
]

log = logging.getLogger(__name__)

OPACITY_SURFACE = 0.5
"""Rendered opacity from which a pixel's depth counts as a surface (IBR, depth .npy)."""


# --------------------------------------------------------------------------- the run
def open_run(out: str | Path, progress: bool = False):
    """The `svolsdf.pipeline.Run` of a finished run with its trained field loaded
    (`svolsdf.pipeline.Run.open`); never runs a stage.

    Args:
        out: a run folder written by ``svolsdf reconstruct`` (config.yaml, views.json,
            field/model.pt; field/stage2/model.pt instead when the finer-stage optimization
            made one).
        progress: progress bars.

    Returns:
        `svolsdf.pipeline.Run` with its scene loaded, ``keys`` set and the field loaded
        (``run.model()`` returns it).

    Raises:
        InputError: OUT is not a run folder, its mode has no field, or field/model.pt is missing
            (the message names the folder).
    """
    from svolsdf.pipeline.loaded_run import Run

    return Run.open(out, progress=progress)


# --------------------------------------------------------------------------- pieces
def box_near_far(cameras_unit: Cameras, bounds: Tensor, min_near: float = 1e-3) -> Tensor:
    """Per-camera z-range of an axis-aligned box: min / max z-depth of its 8 corners.

    Args:
        cameras_unit: V unit-frame cameras.
        bounds: (2, 3) box [[x0, y0, z0], [x1, y1, z1]] in the unit frame.
        min_near: the smallest near value (a camera inside the box starts there).

    Returns:
        (V, 2) float32 [near, far] z-depths, far > near.
    """
    b = torch.as_tensor(bounds, dtype=torch.float64).cpu()
    if b.shape != (2, 3):
        raise ValueError(f"bounds must be (2, 3), got {tuple(b.shape)}")
    idx = torch.cartesian_prod(*[torch.tensor([0, 1])] * 3)  # (8, 3)
    corners = b[idx, torch.arange(3)]  # (8, 3)
    _, z = cameras_unit.to(device="cpu", dtype=torch.float64).project(corners)  # (V, 8)
    near = z.min(1).values.clamp_min(min_near)
    far = torch.maximum(z.max(1).values, near + min_near)
    return torch.stack([near, far], -1).float()


def camera_normals(normals: Tensor, opacity: Tensor, w2c: Tensor) -> Tensor:
    """Normal-map picture: world normals rotated to the camera frame, (n + 1) / 2 x opacity.

    Args:
        normals: (H, W, 3) rendered world-frame normals sum_i w_i n_i (not unit).
        opacity: (H, W) rendered opacity.
        w2c: (4, 4) world-to-camera of the target (unit or world frame: same rotation).

    Returns:
        (3, H, W) float in [0, 1]; OpenCV camera axes (x right, y down, z forward), black where
        nothing was hit.
    """
    n = torch.nn.functional.normalize(normals.float(), dim=-1)
    n = n @ w2c[:3, :3].float().T.cpu()
    img = (n * 0.5 + 0.5) * opacity.clamp(0, 1)[..., None]
    return img.permute(2, 0, 1).clamp(0, 1)


def write_video(frames: list[np.ndarray], stem: Path, fps: int = 20) -> Path:
    """Write frames as ``stem.mp4`` (imageio's ffmpeg backend) or, without one, ``stem.gif``.

    Args:
        frames: N (H, W, 3) uint8 images.
        stem: the path without extension.
        fps: frames per second.

    Returns:
        The written file.
    """
    import imageio.v3 as iio

    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    arr = np.stack(frames)
    try:
        import imageio_ffmpeg  # noqa: F401  (the backend of imageio's mp4 writer)

        # H.264 players want sizes in 16-pixel macro blocks: pad with the edge pixels, else
        # imageio-ffmpeg stretches every frame to fit (and warns on the terminal)
        h, w = arr.shape[1:3]
        arr = np.pad(arr, ((0, 0), (0, -h % 16), (0, -w % 16), (0, 0)), mode="edge")
        path = stem.with_suffix(".mp4")
        iio.imwrite(path, arr, extension=".mp4", fps=fps, codec="libx264")
        log.info("orbit video %s (mp4, %d frames)", path, len(arr))
        return path
    except ImportError:
        raise_if_interrupted()  # an import that Ctrl-C stopped is no missing imageio-ffmpeg
        path = stem.with_suffix(".gif")
        iio.imwrite(path, arr, extension=".gif", duration=1000.0 / fps, loop=0)
        log.info("orbit video %s (GIF: imageio-ffmpeg is not installed, so no MP4; "
                 "pip install imageio-ffmpeg for MP4)", path)
        return path


def _uint8(img: Tensor) -> np.ndarray:
    """(3, H, W) float in [0, 1] -> (H, W, 3) uint8."""
    return (img.clamp(0, 1).permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)


def _parse_size(size) -> tuple[int, int] | None:
    if size is None:
        return None
    w, h = (int(x) for x in size)
    if w < 8 or h < 8:
        raise InputError(f"render size {w}x{h} is too small")
    return w, h


def _scene_range(scene, scale: float) -> Tensor:
    """(V, 2) unit-frame [near, far] of the scene's views, widened as the guide stage does."""
    nf = (scene.depth_range / scale).float()
    return torch.stack([nf[:, 0] * 0.9, nf[:, 1] * 1.1], -1)


# --------------------------------------------------------------------------- the command
def render_outputs(
    out: str | Path,
    views: list[int] | None = None,
    path: str | None = None,
    ibr: bool = False,
    size: tuple[int, int] | list[int] | None = None,
    frames: int = 60,
    chunk: int = 4096,
    fps: int = 20,
    ibr_config=None,
    progress: bool = True,
) -> dict:
    """Render novel views of a finished run (``svolsdf render``; docs/method.md 7).

    Args:
        out: the run folder (config.yaml, views.json, field/model.pt).
        views: scene view ids to render; default the test views of views.json when there are
            any, else the input views. Ignored when ``path`` is given.
        path: "orbit" renders ``frames`` cameras on `svolsdf.ibr.orbit_cameras` through the
            input views instead of scene views.
        ibr: also write the image-based rendering (docs/method.md 7) to OUT/renders_ibr/.
        size: (width, height) to render at (cameras resized with `Cameras.resize`); default
            the run's working size.
        frames: number of orbit frames (>= 2).
        chunk: rays per batch in the volume renderer.
        fps: frame rate of the orbit video.
        ibr_config: `svolsdf.ibr.IBRConfig` (default: the paper's reading).
        progress: a progress bar over the targets.

    Returns:
        dict with "targets" (ids or orbit frame numbers), "files" (written RGB renders),
        "ibr_files", "video" / "video_ibr" (paths or None), "size" [W, H] and
        "seconds_per_view" (volume rendering of one target).

    Raises:
        InputError: not a finished run (see `open_run`), an unknown view id, a bad size or
            path.
    """
    out = Path(out)
    if path is not None and path != "orbit":
        raise InputError(f"--path {path!r}: the only camera path is 'orbit'")
    if path == "orbit" and frames < 2:
        raise InputError(f"--frames {frames}: an orbit needs at least 2 frames")
    if chunk < 1:
        raise InputError(f"--chunk {chunk}: expected a number of rays >= 1")
    from svolsdf.io.paths import output_dir
    from svolsdf.io.runfolder import (
        config_digest,
        file_record,
        folder_lock,
        refuse_in_progress,
    )

    if out.is_dir():
        refuse_in_progress(out)  # not "stopped before it trained the field" while it trains
    p = open_run(out, progress=False)

    changed = p.dir.changed_output("field")
    if changed is not None:
        raise InputError(f"{out}: {changed}; run svolsdf reconstruct -o {out} --config "
                         f"{p.dir.config_file} to train the field again")
    if p.dir.output_provenance(["field"])["field"] == "another config":
        raise InputError(f"{out}: field/model.pt came from an earlier config than "
                         f"{p.dir.config_file} (a rerun with other options stopped before it "
                         f"trained the field again); run svolsdf reconstruct -o {out} --config "
                         f"{p.dir.config_file} first")
    output_dir(out, "run folder")  # renders/ goes there: fail before rendering
    if ibr and ibr_config is not None and ibr_config.hole_depth == "mesh":
        _hole_mesh(p, out, ibr_config)  # a missing or changed mesh: refused before any work
    with folder_lock(out, "svolsdf render"):
        res = _render(p, out, views, path, ibr, size, frames, chunk, fps, ibr_config, progress)
        # evaluate and report check it: renders stay the run's while this field does (a
        # mesh-only change of the config keeps them)
        model = (p.dir.refined_model if p.cfg.mvs.finer_stage_optimization
                 and p.dir.refined_model.is_file() else p.dir.model)
        p.dir.record("render", config_digest(p.dir.config_file),
                     model=model.relative_to(p.dir.root).as_posix(),
                     model_record=file_record(model))
    return res


def mesh_depth_fill(depth: Tensor, cams: Cameras, vertices: np.ndarray, faces: np.ndarray
                    ) -> Tensor:
    """Rendered depth maps with their holes filled by a mesh's depth (``IBRConfig.hole_depth =
    "mesh"``).

    Args:
        depth: (V, H, W) world z-depth, <= 0 where the field rendered no surface.
        cams: `Cameras` of the V views (world frame), any size: rescaled to W x H.
        vertices: (N, 3) world points of the mesh; faces: (F, 3) vertex indices.

    Returns:
        (V, H, W) float32: ``depth`` where it is > 0, else the z-depth of the nearest mesh
        triangle at the pixel centre (`svolsdf.evaluate.raster.rasterize_mesh`), 0 where the
        mesh does not cover the pixel either.
    """
    from svolsdf.evaluate.raster import rasterize_mesh

    V, H, W = depth.shape
    if len(cams) != V:
        raise ValueError(f"mesh_depth_fill: {len(cams)} cameras for {V} depth maps")
    if (cams.width, cams.height) != (W, H):
        cams = cams.resize(W, H)
    out = depth.detach().float().cpu().clone()
    for i in range(V):
        hole = ~(out[i] > 0)
        if not bool(hole.any()):
            continue
        r = rasterize_mesh(vertices, faces, cams.K[i].double().cpu().numpy(),
                           cams.w2c[i].double().cpu().numpy(), W, H)
        z = torch.from_numpy(r.depth).float()
        out[i] = torch.where(hole, z, out[i])
    return out.to(depth.device)


def _hole_mesh(p, out: Path, cfg_ibr) -> tuple[np.ndarray, np.ndarray] | None:
    """The run's mesh (vertices, faces) when ``cfg_ibr.hole_depth == "mesh"``, else None.

    Raises:
        InputError: the run has no mesh.ply (the option names it).
    """
    if cfg_ibr.hole_depth != "mesh":
        return None
    from svolsdf.io.ply import read_ply

    f = out / "mesh.ply"
    if not f.is_file():
        raise InputError(f"--ibr-holes mesh: {f} not found (the run made no mesh; "
                         "run svolsdf reconstruct to the end, or leave --ibr-holes none)")
    changed = p.dir.changed_output("mesh")
    if changed is not None:
        raise InputError(f"--ibr-holes mesh: {out}: {changed}")
    m = read_ply(f)
    if m["faces"] is None or not len(m["faces"]):
        raise InputError(f"--ibr-holes mesh: {f} has no faces")
    return m["points"], m["faces"]


def _render(p, out: Path, views, path, ibr, size, frames, chunk, fps, ibr_config,
            progress) -> dict:
    """`render_outputs` once the run is open and its lock held."""
    from svolsdf.ibr import IBRConfig, ibr_render, orbit_cameras
    from svolsdf.io.images import write_depth_preview, write_image
    from svolsdf.scene.loaders import load_scene

    scene = p.load()
    norm = scene.normalization
    s = float(norm.scale)
    size = _parse_size(size) or (scene.width, scene.height)
    model = p.model()

    # --- target cameras (world) and their unit-frame depth ranges
    if path == "orbit":
        cams_w = orbit_cameras(scene.cameras, frames)
        names = [f"{k:03d}" for k in range(frames)]
        b = model.box()  # a grid's own box (`SurfaceModel.box`), else none
        cams_u = cams_w.transformed(norm.center, s)
        if b is not None:
            near_far = box_near_far(cams_u, b.detach().cpu())
        else:
            r = _scene_range(scene, s)
            near_far = torch.tensor([[float(r[:, 0].min()), float(r[:, 1].max())]]).expand(
                frames, 2).clone()
        rdir, idir = p.dir.renders_dir() / "orbit", p.dir.renders_dir(ibr=True) / "orbit"
        targets: list = list(range(frames))
    else:
        if views is None:
            run_views = p.dir.views()
            if run_views is None or not run_views.inputs:
                log.warning("%s names no input views; the views follow from config.yaml",
                            p.dir.views_file)
                views = list(p.test_view_ids) or list(p.views)
            else:
                views = run_views.test or run_views.inputs
                if not run_views.test:
                    log.warning("%s holds no view out of the run: rendering its input views "
                                "%s, which evaluate scores as input views, not novel ones",
                                out, views)
        views = [int(v) for v in views]
        if not views:
            raise InputError(f"{out}: no views to render")
        tsc = load_scene(scene.path, views=views, image_size=(scene.width, scene.height),
                         load_images=False, lighting=p.cfg.scene.lighting)
        cams_w = tsc.cameras
        names = [str(v) for v in views]
        near_far = _scene_range(tsc, s)
        rdir, idir = p.dir.renders_dir(), p.dir.renders_dir(ibr=True)
        targets = views
    if (cams_w.width, cams_w.height) != size:
        cams_w = cams_w.resize(*size)
    cams_w = cams_w.to(dtype=torch.float64)
    cams_u = cams_w.transformed(norm.center, s)
    W, H = size
    log.info("rendering %d target(s) of %s at %dx%d%s", len(names), out, W, H,
             " with IBR" if ibr else "")

    # --- IBR sources: the input images with their rendered depths, once per call
    src = mesh = None
    if ibr:
        cfg_ibr = ibr_config or IBRConfig()
        mesh = _hole_mesh(p, out, cfg_ibr)
        t0 = time.perf_counter()
        r = p.render_views(scene.cameras_unit, _scene_range(scene, s).to(p.device), chunk=chunk,
                           keys=("depth", "opacity"), desc="IBR: depth of the input views")
        d = r["depth"] * s
        d = torch.where(r["opacity"] >= OPACITY_SURFACE, d, torch.zeros_like(d))
        if mesh is not None:
            d = mesh_depth_fill(d, scene.cameras, *mesh)
        src = (scene.images, scene.cameras.to(dtype=torch.float64), d.float())
        import dataclasses
        import json

        idir.mkdir(parents=True, exist_ok=True)  # which IBR made these files (evaluate reads it)
        (idir / "ibr.json").write_text(json.dumps(dataclasses.asdict(cfg_ibr), indent=1))
        log.info("IBR: rendered the depth of the %d input views in %.1f s", len(scene),
                 time.perf_counter() - t0)

    files, ibr_files, rgb_frames, ibr_frames, secs = [], [], [], [], []
    from svolsdf.io.progress import progress_bar

    what = "render" + (" + IBR" if ibr else "") + (" (orbit)" if path == "orbit" else "")
    for k in progress_bar(range(len(names)), desc=what, show=None if progress else False):
        name = names[k]
        t0 = time.perf_counter()
        r = p.render_views(cams_u[[k]], near_far[[k]].to(p.device), chunk=chunk)
        secs.append(time.perf_counter() - t0)
        rgb = r["rgb"][0].permute(2, 0, 1).clamp(0, 1)  # (3, H, W)
        opa = r["opacity"][0]
        surf = opa >= OPACITY_SURFACE
        depth = torch.where(surf, r["depth"][0] * s, torch.zeros_like(opa))  # world z-depth
        files.append(write_image(rdir / f"{name}.png", rgb))
        p.dir.save_npy(rdir / "depth" / f"{name}.npy", depth.numpy().astype(np.float32))
        write_depth_preview(rdir / "depth" / f"{name}.png", depth, mask=surf)
        write_image(rdir / "normals" / f"{name}.png",
                    camera_normals(r["normals"][0], opa, cams_w.w2c[k]))
        if path == "orbit":
            rgb_frames.append(_uint8(rgb))
        if src is not None:
            if mesh is not None:  # the target's holes too (IBRConfig.hole_depth)
                depth = mesh_depth_fill(depth[None], cams_w[[k]], *mesh)[0]
            res = ibr_render(cams_w[[k]], depth, rgb, src[0], src[1], src[2], cfg_ibr)
            ibr_files.append(write_image(idir / f"{name}.png", res.rgb))
            if path == "orbit":
                ibr_frames.append(_uint8(res.rgb))
            log.debug("ibr %s: %.1f%% of pixels from the sources", name,
                      100 * float(res.weight_sum.mean()))
    video = video_ibr = None
    if path == "orbit":
        video = write_video(rgb_frames, rdir, fps)
        if ibr_frames:
            video_ibr = write_video(ibr_frames, idir, fps)
    spv = float(np.mean(secs)) if secs else None
    log.info("rendered %d view(s) at %dx%d: %.1f s per view (volume rendering)", len(names),
             W, H, spv or 0.0)
    return {"targets": targets, "files": files, "ibr_files": ibr_files, "video": video,
            "video_ibr": video_ibr, "size": [W, H], "seconds_per_view": spv}
