"""Surface snapshots during the field's optimization (``train.snapshot_every``) and the figure
they make: the surface over the optimization seen from the first input view.

Each snapshot is the field's zero level on a coarse grid (`SNAPSHOT_RESOLUTION` points a side,
`svolsdf.fusion.meshing.field_mesh`, culled to the input views as the mesh stage culls), in world
units, written to OUT/field/snapshots/step_NNNNNN.ply; a snapshot that fails (no zero level yet)
is a warning, not a failed run. The figure, OUT/field/snapshots/snapshots.png, shades each
snapshot from the first input view (`svolsdf.evaluate.raster`)."""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from pathlib import Path

import torch

from svolsdf.errors import raise_if_interrupted
from svolsdf.pipeline.context import StageContext

__all__ = ["SNAPSHOT_RESOLUTION", "snapshot_figure", "snapshot_writer", "write_snapshot_figure"]

log = logging.getLogger("svolsdf.pipeline")

SNAPSHOT_RESOLUTION = 96
"""Grid points per side of a snapshot's marching cubes: coarse, so that a snapshot costs a
fraction of the steps between two."""


def snapshot_folder(p: StageContext) -> Path:
    return p.dir.field_dir / "snapshots"


def snapshot_writer(p: StageContext, model, start: int) -> Callable[[int], None] | None:
    """The ``on_step`` of the field's `Trainer.fit` that writes a snapshot every
    ``train.snapshot_every`` steps (and one of the surface at ``start``, the step the fit
    starts from); None when the option is 0."""
    every = p.cfg.train.snapshot_every
    if every <= 0:
        return None
    from svolsdf.fusion.meshing import field_mesh
    from svolsdf.io.ply import write_mesh_ply

    folder = snapshot_folder(p)
    folder.mkdir(parents=True, exist_ok=True)
    scene = p.load()
    b = model.box()  # a grid's own box, else the field's (`SurfaceModel.box`)
    bounds = b.detach().cpu() if b is not None else p.field_bounds()

    def snap(step: int) -> None:
        if step % every and step != start:
            return
        try:
            with torch.no_grad():
                _, vw, f = field_mesh(model, bounds, scene, SNAPSHOT_RESOLUTION,
                                      use_masks=p.cfg.scene.use_masks, depths=None,
                                      device=p.device)
            write_mesh_ply(folder / f"step_{step:06d}.ply", vw.numpy(), f.numpy())
        except Exception as e:  # a picture of the training must not stop it
            raise_if_interrupted()
            log.warning("surface snapshot at step %d failed: %s", step, e)

    snap(start)
    return snap


def snapshot_figure(folder: Path, cameras, path: Path, columns: int = 4) -> Path | None:
    """A grid of the snapshots in ``folder`` (step order), each shaded from ``cameras[0]``
    (`svolsdf.scene.Cameras`, resized to at most 320 px across), written to ``path`` (PNG);
    None when there are no snapshots."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    import numpy as np

    from svolsdf.evaluate.raster import rasterize_mesh, shade, vertex_normals
    from svolsdf.io.ply import read_ply

    files = sorted(Path(folder).glob("step_*.ply"))
    if not files:
        return None
    cam = cameras.to(dtype=torch.float64)
    if cam.width > 320:
        cam = cam.resize(320, max(8, round(cam.height * 320 / cam.width)))
    K, w2c = cam.K[0].numpy(), cam.w2c[0].numpy()
    rows = (len(files) + columns - 1) // columns
    cols = min(columns, len(files))
    fig, axes = plt.subplots(rows, cols, squeeze=False,
                             figsize=(2.6 * cols, 2.6 * rows * cam.height / cam.width + 0.3))
    for ax in axes.ravel():
        ax.axis("off")
    for ax, f in zip(axes.ravel(), files, strict=False):
        d = read_ply(f)
        v, faces = np.asarray(d["points"], np.float64), d["faces"]
        if faces is not None and len(faces):
            r = rasterize_mesh(v, faces, K, w2c, cam.width, cam.height)
            pic, _ = shade(r, faces, vertex_normals(v, faces), w2c)
        else:
            pic = np.full((cam.height, cam.width, 3), 255, np.uint8)
        ax.imshow(pic)
        ax.set_title(f"step {int(re.sub(r'[^0-9]', '', f.stem))}", fontsize=9)
    fig.tight_layout()
    from svolsdf.io.images import save_figure

    return save_figure(fig, path)


def write_snapshot_figure(p: StageContext) -> Path | None:
    """OUT/field/snapshots/snapshots.png from the run's snapshots (`snapshot_figure`); a
    failure is a warning."""
    folder = snapshot_folder(p)
    try:
        return snapshot_figure(folder, p.load().cameras, folder / "snapshots.png")
    except Exception as e:  # a convenience
        raise_if_interrupted()
        log.warning("snapshot figure failed: %s", e)
        return None
