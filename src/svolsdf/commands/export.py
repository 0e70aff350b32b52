"""``svolsdf export OUT``: a finished run in the formats other tools open.

Written into DEST (default OUT/export), all of it or nothing (`svolsdf.io.replace`: a new
folder inside DEST, swapped in at the end; a failure or Ctrl-C leaves DEST as it was):

- ``images/``: copies of the input photos the cameras below describe (at their file size);
- ``transforms.json``: the cameras for nerfstudio (`svolsdf.scene.camera_export`), its
  ``ply_file_path`` naming points.ply;
- ``sparse/0/``: a COLMAP model written by pycolmap (cameras, images, points3D and the rigs
  and frames of COLMAP >= 3.12), the fused points with the input views that observe them (their
  final depth agrees) as tracks; with ``images/`` beside it DEST is a COLMAP scene (the layout
  COLMAP's own projects, gaussian splatting and ``svolsdf reconstruct`` read);
- ``cameras.json``: K, R, t per view in the scene's world frame and units;
- ``points.ply``: the fused points with outward normals (nx, ny, nz; oriented as the Poisson
  mesher orients them, `svolsdf.fusion.meshing.oriented_normals`) and colours;
- ``meshes/<method>.ply``: the mesh of each mesh method side by side (OUT/mesh.ply copied as its
  method's, the others made from the run's field, points and depth as the mesh stage makes
  them; a method that gives no surface is left out and named);
- ``mesh_coloured.ply``: OUT/mesh.ply with vertex colours from the input photos, each vertex
  averaged over the views that see it (its depth agrees with the view's rasterized mesh);
- ``mesh_textured.obj`` (+ ``.mtl``, ``.png``): OUT/mesh.ply with a texture atlas baked from
  the photos the same way (`svolsdf.fusion.texture`).

The run folder itself is only read. Runs without a field (mvs-only) have no mesh: DEST then
holds the cameras and the points.
"""

from __future__ import annotations

import copy
import json
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from svolsdf.errors import InputError
from svolsdf.io.replace import OutputSpec, replace_outputs
from svolsdf.io.runfolder import RunFolder, refuse_in_progress

__all__ = ["EXPORT_OUTPUT", "ExportResult", "check_finished_run", "export_run", "mesh_depths",
           "mesh_photo_colours", "points_seen"]

log = logging.getLogger(__name__)

EXPORT_OUTPUT = OutputSpec(
    command="svolsdf export",
    names=frozenset({"images", "transforms.json", "sparse", "cameras.json", "points.ply",
                     "meshes", "mesh_coloured.ply", "mesh_textured.obj", "mesh_textured.mtl",
                     "mesh_textured.png"}),
    what="export folder", earlier="an earlier svolsdf export")
"""What ``svolsdf export`` writes into its folder."""


@dataclass
class ExportResult:
    """What `export_run` wrote.

    Attributes:
        dest: the export folder.
        files: the entries written at its top.
        meshes: {method: DEST/meshes/<method>.ply} of the meshes made.
        skipped: {what: why} of what was not made (a mesh method without a surface, ...).
    """

    dest: Path
    files: list[str] = field(default_factory=list)
    meshes: dict[str, Path] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)


def check_finished_run(out: str | Path):
    """The config of the finished run in ``out``; refuses anything else, writing nothing.

    Returns:
        the run's validated `svolsdf.config.Config`.

    Raises:
        InputError: ``out`` is missing, not a run folder of ``svolsdf reconstruct``, being
            written by another command, unfinished (its last stage has not finished), or its
            points.ply or mesh.ply changed since their stage finished or came from an earlier
            config; one line naming the folder and the way out.
    """
    from svolsdf.config import load_config, validate_config
    from svolsdf.io.paths import input_dir
    from svolsdf.pipeline.options import has_field

    out = input_dir(out, "run folder")
    run = RunFolder(out)
    missing = run.missing_run_files()
    if missing:
        raise InputError(f"{out}: not a run folder ({missing} missing); give the output folder "
                         "of svolsdf reconstruct")
    refuse_in_progress(out)
    cfg = validate_config(load_config(run.config_file))
    again = f"svolsdf reconstruct -o {out} --config {run.config_file}"
    last, needed = ("mesh", run.mesh()) if has_field(cfg) else ("fusion", run.points)
    if last not in run.stage_state() or not needed.is_file() or not run.points.is_file():
        raise InputError(f"{out}: the run is not finished (stage {last} has not finished, "
                         f"{needed.name} is missing); run {again} to finish it first")
    for stage in ("fusion", last):
        why = run.changed_output(stage)
        if why is not None:
            raise InputError(f"{out}: {why}; run {again} to make it again")
    names = ["points.ply"] + (["mesh.ply"] if last == "mesh" else [])
    stale = [n for n, v in run.output_provenance(names).items() if v == "another config"]
    if stale:
        raise InputError(f"{out}: {', '.join(stale)} came from an earlier config than "
                         f"{run.config_file}; run {again} first")
    return cfg


def export_run(out: str | Path, dest: str | Path | None = None,
               progress: bool = False) -> ExportResult:
    """Export the finished run in ``out`` into ``dest`` (default OUT/export): see the module
    docstring for what is written.

    Raises:
        InputError: a bad ``out`` (`check_finished_run`) or ``dest`` (not empty and not an
            earlier export, a file, ...), before anything is written; a scene folder that moved
            since the run.
    """
    from svolsdf.pipeline.loaded_run import Run
    from svolsdf.pipeline.options import has_field

    cfg = check_finished_run(out)
    out = Path(out).expanduser()
    dest = out / "export" if dest is None else Path(dest)
    from svolsdf.io.replace import check_replace

    check_replace(dest, EXPORT_OUTPUT, [out])
    run = Run.open(out, progress=progress, field=has_field(cfg))
    run.load()  # the scene as the run used it: a moved scene folder ends here
    res = ExportResult(dest=dest)
    with replace_outputs(dest, EXPORT_OUTPUT, [out]) as stage:
        _write_cameras(run, stage)
        _write_points(run, stage)
        if run.has_field():
            _write_meshes(run, stage, res)
            _write_coloured_mesh(run, stage, res)
        res.files = sorted(p.name for p in stage.iterdir())
    res.meshes = {m: dest / "meshes" / f"{m}.ply" for m in res.meshes}
    return res


# --------------------------------------------------------------------------- cameras
def _native_cameras(run):
    """The input views' cameras at the size of their image files, and the files."""
    from svolsdf.scene.loaders import load_scene

    sc = run.cfg.scene
    head = load_scene(sc.path, views=run.views, load_images=False, lighting=sc.lighting)
    return head.cameras, head.image_paths


def _image_names(paths: list[Path], view_ids: list[int]) -> list[str]:
    """A file name per input photo, unique (the view id in front where two share one)."""
    names = [p.name for p in paths]
    if len(set(names)) < len(names):
        names = [f"{v}_{n}" for v, n in zip(view_ids, names, strict=True)]
    return names


def _write_cameras(run, stage: Path) -> None:
    from svolsdf.io.ply import read_ply
    from svolsdf.scene.camera_export import (
        camera_json,
        colmap_reconstruction,
        nerfstudio_transforms,
    )

    scene = run.load()
    cams, paths = _native_cameras(run)
    names = _image_names(paths, run.views)
    (stage / "images").mkdir()
    for p, n in zip(paths, names, strict=True):
        shutil.copyfile(p, stage / "images" / n)
    files = [f"images/{n}" for n in names]
    _write_json(stage / "transforms.json",
                nerfstudio_transforms(cams, files, points_file="points.ply"))
    _write_json(stage / "cameras.json",
                camera_json(cams, run.views, files, scene.units, scene.path, scene.format,
                            scene.normalization))
    pts = read_ply(run.dir.points)
    depths = _final_depths(run)
    seen = None if depths is None else points_seen(pts["points"], scene.cameras, depths)
    rec = colmap_reconstruction(cams, names, pts["points"], pts["colors"], seen)
    (stage / "sparse" / "0").mkdir(parents=True)
    rec.write(str(stage / "sparse" / "0"))


def _final_depths(run) -> list[torch.Tensor] | None:
    """The input views' final depth maps (OUT/depth/<id>.npy), or None when one is missing."""
    files = [run.dir.depth_dir / f"{v}.npy" for v in run.views]
    if not all(f.is_file() for f in files):
        return None
    return [torch.from_numpy(np.load(f)).float() for f in files]


def points_seen(points: np.ndarray, cameras, depths: list[torch.Tensor],
                rel_tol: float = 0.01) -> np.ndarray:
    """Which views observe each point: it projects inside the view in front of the camera and
    its z-depth is within ``rel_tol`` of the view's depth map at the nearest pixel.

    Args:
        points: (N, 3) world points.
        cameras: V world `Cameras`.
        depths: V (H, W) z-depth maps (world units, 0 = none), at any size.
        rel_tol: relative depth tolerance.

    Returns:
        (N, V) bool.
    """
    if len(depths) != len(cameras):
        raise ValueError(f"depths: {len(depths)} maps for {len(cameras)} cameras")
    x = torch.from_numpy(np.asarray(points, np.float64))
    out = np.zeros((len(x), len(cameras)), bool)
    for v, d in enumerate(depths):
        h, w = d.shape
        uv, z = cameras[v].resize(w, h).to(dtype=torch.float64).project(x[None])
        px, z = uv[0].round().long(), z[0]
        ok = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        dv = torch.zeros_like(z)
        dv[ok] = d.double()[px[ok, 1], px[ok, 0]]
        out[:, v] = (ok & (dv > 0) & ((z - dv).abs() <= rel_tol * z)).numpy()
    return out


# --------------------------------------------------------------------------- points
def _write_points(run, stage: Path) -> None:
    from svolsdf.fusion.meshing import oriented_normals
    from svolsdf.io.ply import read_ply, write_points_ply

    pts = read_ply(run.dir.points)
    normals = None
    if len(pts["points"]) > 16:
        model = run.model() if run.has_field() else None
        normals = oriented_normals(pts["points"], run.load(), model, device=run.device)
    else:
        log.warning("%s: %d points, too few for normals; written without them",
                    run.dir.points, len(pts["points"]))
    write_points_ply(stage / "points.ply", pts["points"], pts["colors"], normals=normals)


# --------------------------------------------------------------------------- meshes
class _MeshContext:
    """The run as `svolsdf.pipeline.mesh.build_mesh` reads it, under another mesh config; what
    the mesh stage would save (the field fitted to the points) goes to ``scratch``, not OUT."""

    def __init__(self, run, cfg, scratch: Path):
        from svolsdf.pipeline.rundir import RunDir

        class _Dir(RunDir):
            @property
            def surface_model(self) -> Path:
                return scratch / "surface.pt"

        self.cfg, self.dir, self.out = cfg, _Dir(run.out), run.out
        self.views, self.device, self.progress = run.views, run.device, run.progress
        self._run = run

    def load(self):
        return self._run.load()

    def model(self):
        return self._run.model()

    def field_bounds(self):
        return self._run.field_bounds()


def _write_meshes(run, stage: Path, res: ExportResult) -> None:
    """DEST/meshes/<method>.ply for every registered mesh method (`ExportResult.skipped` names
    those without a surface)."""
    from svolsdf.fusion.mesh_methods import registered_mesh_methods
    from svolsdf.io.ply import write_mesh_ply
    from svolsdf.pipeline.mesh import build_mesh

    folder = stage / "meshes"
    folder.mkdir()
    source = run.dir.mesh_source() or ("field" if run.cfg.mesh.watertight
                                       else run.cfg.mesh.method)
    own = source.split(" ")[0]
    shutil.copyfile(run.dir.mesh(), folder / f"{own}.ply")
    res.meshes[own] = folder / f"{own}.ply"
    for name in registered_mesh_methods():
        if name == own:
            continue
        cfg = copy.deepcopy(run.cfg)
        cfg.mesh.method, cfg.mesh.watertight = name, False
        log.info("export: the %s mesh", name)
        try:
            ctx = _MeshContext(run, cfg, stage)
            vw, f, cols, info = build_mesh(ctx, ctx.model())
        except (RuntimeError, ValueError) as e:
            res.skipped[f"meshes/{name}.ply"] = " ".join(str(e).split())[:200]
            continue
        finally:
            (stage / "surface.pt").unlink(missing_ok=True)
        if info["mesh_source"] != name:  # the method failed and the field's mesh stood in
            res.skipped[f"meshes/{name}.ply"] = info["mesh_source"]
            continue
        write_mesh_ply(folder / f"{name}.ply", vw, f, cols)
        res.meshes[name] = folder / f"{name}.ply"


def _write_coloured_mesh(run, stage: Path, res: ExportResult) -> None:
    """OUT/mesh.ply with vertex colours from the input photos (`mesh_photo_colours`), and as
    an OBJ with a texture atlas baked from them (`svolsdf.fusion.texture.bake_atlas`)."""
    from svolsdf.fusion.texture import bake_atlas
    from svolsdf.io.ply import read_ply, write_mesh_ply, write_textured_obj

    m = read_ply(run.dir.mesh())
    scene = run.load()
    depths = mesh_depths(m["points"], m["faces"], scene.cameras)
    cols = mesh_photo_colours(m["points"], m["faces"], scene, depths)
    write_mesh_ply(stage / "mesh_coloured.ply", m["points"], m["faces"], cols)
    try:
        uv, texture = bake_atlas(m["points"], m["faces"], scene.images, scene.cameras, depths)
    except ValueError as e:  # more faces than an atlas holds
        res.skipped["mesh_textured.obj"] = str(e)
        return
    write_textured_obj(stage / "mesh_textured.obj", m["points"], m["faces"], uv, texture)


def mesh_depths(vertices: np.ndarray, faces: np.ndarray, cameras) -> torch.Tensor:
    """(N, H, W) each camera's z-depth of the mesh (0 where it shows none), by its z-buffer
    (`svolsdf.evaluate.raster.rasterize_mesh`)."""
    from svolsdf.evaluate.raster import rasterize_mesh

    K, w2c = cameras.K.double().numpy(), cameras.w2c.double().numpy()
    return torch.stack([torch.from_numpy(rasterize_mesh(vertices, faces, K[v], w2c[v],
                                                        cameras.width, cameras.height).depth)
                        for v in range(len(cameras))])


def mesh_photo_colours(vertices: np.ndarray, faces: np.ndarray, scene,
                       depths: torch.Tensor | None = None, rel_tol: float = 0.01) -> np.ndarray:
    """Vertex colours from the scene's photos: the mean over the views that see each vertex,
    a view seeing it when the vertex's z-depth agrees (within ``rel_tol``) with the view's
    z-buffer of the mesh itself (`mesh_depths`); grey where none does
    (`svolsdf.fusion.mesh_ops.colors_from_images`).

    Args:
        vertices: (V, 3) world points; faces: (F, 3).
        scene: `Scene` with images (N, 3, H, W) and world cameras.
        depths: `mesh_depths` of the mesh, or None to compute them.

    Returns:
        (V, 3) uint8.
    """
    from svolsdf.fusion.mesh_ops import colors_from_images, vertex_normals

    cams = scene.cameras
    if depths is None:
        depths = mesh_depths(vertices, faces, cams)
    vt, ft = torch.from_numpy(np.asarray(vertices)), torch.from_numpy(np.asarray(faces))
    return colors_from_images(vt, vertex_normals(vt, ft), scene.images, cams, depths=depths,
                              depth_rel_tol=rel_tol).numpy()


def _write_json(path: Path, obj: dict) -> None:
    path.write_text(json.dumps(obj, indent=1) + "\n")
