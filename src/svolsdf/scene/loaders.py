"""`load_scene`: detect a scene folder's format and read it into a `Scene`.

Formats (docs/method.md 1.1-1.3; readers in `svolsdf.scene.formats`, registered with
``@register_scene_format``), in detection order:

- ``idr``: IDR / VolSDF / NeuS, ``cameras.npz`` or ``cameras_sphere.npz`` + ``image(s)/``
  [+ ``mask/``]
- ``dtu_raw``: ``Rectified/scanN/rect_XXX_L_r5000.*`` + ``Calibration/cal18/pos_XXX.txt``
- ``mvsnet``: MVSNet / BlendedMVS, ``cams/*_cam.txt`` + ``images/`` or ``blended_images/``
- ``colmap``: ``sparse/0`` or ``sparse/`` (text or binary) + ``images/``
- ``nerf``: ``transforms.json``

Where the files do not say, this module fills in (in order of preference):

- pairs: ``pair.txt``; else MVSNet's view selection (`svolsdf.scene.pairs`) on the sparse points,
  else on points sampled in the normalization sphere;
- normalization: ``scale_mat``; else VolSDF's rule (docs/method.md 1.2) around the sparse points'
  median, else around the point nearest all optical axes;
- depth range per view: the file's (MVSNet); DTU's standard range (docs/method.md 1.1: 425 mm + 2.65
  mm x 192 planes) for DTU scans; else the sparse points' depths; else the normalization sphere.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from svolsdf.errors import InputError
from svolsdf.io.images import (
    ImageReadError,
    image_size,
    read_image,
    read_mask,
    resize_image,
    resize_mask,
)
from svolsdf.io.paths import input_dir, path_label, user_path
from svolsdf.scene.cameras import Cameras
from svolsdf.scene.formats import SceneSource, get_scene_format, scene_formats
from svolsdf.scene.normalize import (
    normalization_from_points,
    normalize_cameras,
    points_depth_range,
    sphere_depth_range,
)
from svolsdf.scene.pairs import compute_pairs
from svolsdf.scene.scene import Scene, SceneError, _id_summary

__all__ = ["DTU_DEPTH_MIN", "DTU_DEPTH_INTERVAL", "detect_format", "load_scene", "read_source",
           "scene_folder"]

log = logging.getLogger(__name__)

# docs/method.md 1.1 / 1.4: the released code's hard-coded DTU range, d_k = 425 + 2.65 k, 192
# planes.
DTU_DEPTH_MIN = 425.0
DTU_DEPTH_INTERVAL = 2.65
DTU_NUM_DEPTH = 192

def scene_folder(path: str | Path, option: str | None = None) -> Path:
    """The scene folder ``path`` (``~`` expanded, `svolsdf.io.paths.user_path`) once a
    registered format reads its layout.

    Args:
        path: the folder as the user gave it.
        option: the option that gave it (``--scenes``), for the message; None for an argument.

    Raises:
        SceneError: the folder is missing, a dangling link, a file or unreadable
            (`svolsdf.io.paths.input_dir` names the cause), or no known layout is found (the
            message lists what each format looks for).
    """
    _, p = _detect(path, option)
    return p


def _detect(path: str | Path, option: str | None = None) -> tuple[str, Path]:
    """(format name, the expanded folder) of ``path`` (`scene_folder`)."""
    try:
        p = input_dir(path, "scene folder", option)
    except InputError as e:
        raise SceneError(str(e)) from None
    formats = scene_formats()
    for fmt in formats:
        if fmt.detect(p):
            return fmt.name, p
    looked_for = "; ".join(f.looks_for for f in formats)
    raise SceneError(f"{path_label(path, option)}: no known scene layout found (looked for "
                     f"{looked_for})")


def detect_format(path: str | Path) -> str:
    """Name of the scene format found at ``path``: the first registered format, in detection
    order, whose ``detect`` accepts it (`svolsdf.scene.formats.scene_formats`).

    Raises:
        SceneError: as `scene_folder`.
    """
    return _detect(path)[0]


def read_source(path: str | Path, lighting: int | str = 3) -> SceneSource:
    """Detect the format and read cameras and file lists, without pixels."""
    name, path = _detect(path)
    return get_scene_format(name).read(path, lighting=lighting)


def _declared_units(folder: Path) -> str | None:
    """The world units that the scene folder's scene.json declares (``svolsdf synth`` writes
    ``"units": "mm"``), or None when it has no such file or names none (a scene made with the
    cameras of another keeps theirs: "as in cameras_from")."""
    import json

    try:
        units = json.loads((Path(folder) / "scene.json").read_text()).get("units")
    except (OSError, ValueError, AttributeError):
        return None
    ok = isinstance(units, str) and units.strip() and not units.startswith("as in")
    return units.strip() if ok else None


def _is_dtu(src: SceneSource, size: tuple[int, int]) -> bool:
    # DTU: 49 (or all 64) rig positions of 1600x1200 images.
    return src.format == "dtu_raw" or (
        src.format in ("idr", "mvsnet") and len(src.view_ids) in (49, 64)
        and size == (1600, 1200))


def _image_size(p: Path) -> tuple[int, int]:
    try:
        return image_size(p)
    except FileNotFoundError:
        raise SceneError(f"{p}: image file does not exist") from None
    except ImageReadError as e:
        raise SceneError(str(e)) from None


def load_scene(path: str | Path, views: list[int] | None = None,
               image_size: tuple[int, int] | None = None, load_images: bool = True,
               lighting: int | str = 3, masks: bool = True) -> Scene:
    """Read a scene folder in any supported format (module docstring) into a `Scene`.

    Args:
        path: the scene folder (for DTU raw: the dataset root holding one scan, or
            ``Rectified/scanN``).
        views: view ids to keep, in this order; default all, in file order.
        image_size: (width, height) to resize images (bicubic, antialiased when shrinking) and
            cameras (`Cameras.resize`) to; default the files' size.
        load_images: False leaves ``images`` and ``masks`` None but still reads the image size
            from the file headers (fast; for ``svolsdf info``).
        lighting: DTU raw lighting index 0..6 or "max".
        masks: load masks when the scene has them.

    Returns:
        `Scene` with images (V, 3, H, W) float32, masks (V, 1, H, W) or None, cameras in world
        units at the working size, pairs over all views of the file, depth_range (V, 2).

    Raises:
        SceneError: a missing folder, unknown layout, unreadable image, mismatched counts,
            non-finite or singular cameras, images of different sizes, or an unknown view id;
            the message names the file and the problem.
    """
    path = user_path(path)
    src = read_source(path, lighting=lighting)
    n_all = len(src.view_ids)

    # --- which views
    if views is None:
        idx = list(range(n_all))
    else:
        if len(views) == 0:
            raise SceneError(f"{path}: no view ids given")
        repeated = sorted({v for v in views if list(views).count(v) > 1})
        if repeated:
            raise SceneError(f"{path}: view id {repeated[0]} is given more than once (views "
                             f"{list(views)}); give each view once")
        idx = []
        for v in views:
            try:
                idx.append(src.view_ids.index(int(v)))
            except ValueError:
                raise SceneError(f"{path}: view id {v} does not exist (available: "
                                 f"{_id_summary(src.view_ids)})") from None
    view_ids = [src.view_ids[i] for i in idx]
    image_paths = [src.image_paths[i] for i in idx]

    # --- image size (headers only), the same for all selected views
    size = _image_size(image_paths[0])
    for p in image_paths[1:]:
        s = _image_size(p)
        if s != size:
            raise SceneError(f"{p} is {s[0]}x{s[1]} but {image_paths[0]} is {size[0]}x{size[1]}; "
                             f"all images must have one size")
    if src.camera_size is not None and tuple(src.camera_size) != size:
        raise SceneError(f"{src.cameras_file} gives cameras for {src.camera_size[0]}x"
                         f"{src.camera_size[1]} images but {image_paths[0]} is "
                         f"{size[0]}x{size[1]}")
    _check_fit(src, idx, image_paths, size)
    cams_all = Cameras(src.K.double(), src.w2c.double(), size[0], size[1])
    dtu = _is_dtu(src, size)
    units = "mm" if dtu else src.units
    if units == "unknown":
        units = _declared_units(path) or units
    extras = dict(src.extras)
    if dtu:
        extras["dtu"] = True

    # --- normalization (from all views of the file, so it does not depend on ``views``)
    norm = src.normalization
    if norm is not None:
        extras["normalization_source"] = "scale_mat"
    elif src.points is not None and len(src.points) > 0:
        norm = normalization_from_points(src.points, cams_all)
        extras["normalization_source"] = "sparse points (median) + VolSDF scale rule"
    else:
        norm = normalize_cameras(cams_all)
        extras["normalization_source"] = "VolSDF normalize_cameras (docs/method.md 1.2)"

    # --- depth range per view
    if src.depth_range is not None:
        depth = src.depth_range.double()
        extras["depth_range_source"] = "file"
    elif dtu:
        far = DTU_DEPTH_MIN + DTU_DEPTH_INTERVAL * DTU_NUM_DEPTH
        depth = torch.tensor([[DTU_DEPTH_MIN, far]], dtype=torch.float64).expand(n_all, 2).clone()
        extras["depth_range_source"] = "DTU standard (docs/method.md 1.1: 425 + 2.65 k, 192 planes)"
    else:
        depth = sphere_depth_range(cams_all, norm)
        extras["depth_range_source"] = "object sphere (unit-frame radius 1)"
        if src.points is not None and len(src.points) > 0:
            pr, counts = points_depth_range(cams_all, src.points, src.visibility)
            ok = torch.isfinite(pr).all(-1)
            depth[ok] = pr[ok]
            extras["depth_range_source"] = ("sparse points" if ok.all() else
                                            f"sparse points ({int(ok.sum())} views), "
                                            f"normalization sphere (others)")

    # --- pairs (over all views of the file)
    if src.pairs is not None:
        pairs, scores = src.pairs, src.pair_scores
        extras["pairs_source"] = "pair.txt"
    else:
        pairs, scores = compute_pairs(cams_all, src.view_ids, points=src.points,
                                      visibility=src.visibility, normalization=norm)
        extras["pairs_source"] = ("view selection on sparse points" if src.points is not None
                                  else "view selection on points sampled in the normalization "
                                       "sphere")
    extras["pair_scores"] = scores

    # --- masks
    mask_paths = None
    if src.mask_paths is not None:
        mask_paths = [src.mask_paths[i] for i in idx]
        if any(p is None for p in mask_paths):
            # a folder with the masks of some views (BlendedMVS' evaluation masks): kept for
            # the evaluation (extras "eval_mask_paths"), used by the run only when every
            # loaded view has one
            have = {v: str(p) for v, p in zip(view_ids, mask_paths, strict=True) if p is not None}
            extras["eval_mask_paths"] = have
            log.info("%s: masks of %d of the %d loaded views: used for evaluation only, the run "
                     "uses none", src.path, len(have), len(mask_paths))
            mask_paths = None
    elif src.masks_from_alpha:
        with_alpha = _has_alpha(image_paths[0])
        mask_paths = image_paths if with_alpha else None
    if mask_paths is not None:
        extras["mask_paths"] = [str(p) for p in mask_paths]
        for p in mask_paths:
            s = _image_size(p)
            if s != size:
                raise SceneError(f"mask {p} is {s[0]}x{s[1]} but the images are "
                                 f"{size[0]}x{size[1]}")

    # --- pixels
    W, H = image_size if image_size is not None else size
    images = mask_t = None
    if load_images:
        images = torch.empty(len(idx), 3, H, W, dtype=torch.float32)
        for k, p in enumerate(image_paths):
            images[k] = resize_image(_read(read_image, p, src.background), W, H)
        if masks and mask_paths is not None:
            mask_t = torch.empty(len(idx), 1, H, W, dtype=torch.float32)
            for k, p in enumerate(mask_paths):
                mask_t[k] = resize_mask(_read(read_mask, p), W, H)

    cams = cams_all[idx]
    if (W, H) != size:
        cams = cams.resize(W, H)
    extras["native_size"] = size
    if src.background is not None:
        extras["background"] = src.background
    return Scene(
        images=images, cameras=cams, view_ids=view_ids, masks=mask_t, pairs=pairs,
        depth_range=depth[idx], normalization=norm, path=src.path, format=src.format,
        units=units, image_paths=image_paths, extras=extras,
    )


def _check_fit(src: SceneSource, idx: list[int], image_paths: list[Path],
               size: tuple[int, int]) -> None:
    """Refuse images that do not fit their cameras: a principal point outside the image (the
    cameras are for images of another size or crop, and every ray would be wrong)."""
    W, H = size
    c = src.K[idx][:, :2, 2].double()
    out = ((c[:, 0] < -0.5) | (c[:, 0] > W - 0.5) | (c[:, 1] < -0.5) | (c[:, 1] > H - 0.5))
    if bool(out.any()):
        k = int(out.nonzero()[0, 0])
        cx, cy = (float(v) for v in c[k])
        raise SceneError(f"{image_paths[k]} is {W}x{H} but its camera ({src.camera_source[idx[k]]}"
                         f") has its principal point at ({cx:.1f}, {cy:.1f}), outside the image: "
                         f"the cameras are for images of about {2 * cx + 1:.0f}x{2 * cy + 1:.0f}; "
                         "give the images the size the cameras were calibrated at")


def _read(fn, p: Path, *args):
    try:
        return fn(p, *args)
    except FileNotFoundError:
        raise SceneError(f"{p}: image file does not exist") from None
    except ImageReadError as e:
        raise SceneError(str(e)) from None


def _has_alpha(p: Path) -> bool:
    from PIL import Image

    try:
        with Image.open(p) as im:
            return "A" in im.getbands() or (im.mode == "P" and "transparency" in im.info)
    except Image.DecompressionBombError:
        _image_size(p)  # the one message for an image too large to read
        raise
    except OSError:
        return False
