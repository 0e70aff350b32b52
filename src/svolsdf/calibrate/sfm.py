"""`calibrate`: structure from motion with pycolmap on photos or video frames, written as a scene.

Steps (COLMAP's incremental pipeline, Schoenberger and Frahm, CVPR 2016):

1. inputs (`svolsdf.calibrate.inputs`): photos oriented and shrunk to ``max_size``, or frames
   sampled from a video; one shared camera when the photos say so (same size and EXIF camera);
2. SIFT features, matching (exhaustive, or sequential for ordered frames) with geometric
   verification, incremental mapping with bundle adjustment (SIMPLE_RADIAL cameras);
3. the largest model is kept; its images are undistorted to a pinhole camera of the same size
   and focal length, so ``SCENE`` is a COLMAP model that `svolsdf.scene.formats.colmap` reads
   without ignoring distortion::

       SCENE/images/<name>                 the registered photos (undistorted)
       SCENE/sparse/0/cameras.txt          PINHOLE cameras
       SCENE/sparse/0/images.txt           poses and (undistorted) 2D points
       SCENE/sparse/0/points3D.txt         sparse points with their tracks
       SCENE/calibration.json              inputs, registered / unregistered photos, timings,
                                           reprojection error, pycolmap version

pycolmap's Python API changes between versions; this module only calls ``Database.open``,
``import_images``, ``extract_features``, ``match_exhaustive`` / ``match_sequential``,
``incremental_mapping`` and ``Reconstruction.write_text`` and reads the model back from COLMAP's
documented text format.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from svolsdf.calibrate.inputs import Photo, gather_inputs, shared_camera
from svolsdf.errors import InputError
from svolsdf.io.replace import OutputSpec, check_replace, replace_outputs

__all__ = ["CalibrateConfig", "CalibrationError", "calibrate", "num_threads",
           "undistort_simple_radial"]

log = logging.getLogger(__name__)

MATCHERS = ("auto", "exhaustive", "sequential")
_INSTALL = "pip install 'svolsdf[colmap]'  (or: pip install pycolmap)"


class CalibrationError(InputError):
    """Structure from motion did not register enough photos; the message says what helps."""


@dataclass
class CalibrateConfig:
    """Options of ``svolsdf calibrate``."""

    max_size: int | None = 1600
    """Longest image side in pixels for SfM and for SCENE/images (None: the photos' size)."""
    matcher: str = "auto"
    """exhaustive (every pair: best for photos), sequential (neighbouring frames: fast for a
    video) or auto (sequential for a video, exhaustive for photos)."""
    frames: int = 40
    """Frames sampled evenly from a video."""
    max_features: int = 8192
    """SIFT features per image."""
    min_registered: int = 3
    """Fewest registered photos accepted (S-VolSDF needs 3 views)."""
    threads: int = 0
    """CPU threads for structure from motion; 0 = the cores this process may run on (as
    reconstruct's --threads)."""
    seed: int = 0
    """Random seed of the mapper (same inputs, same cameras)."""
    progress: bool = True
    """Show progress bars."""


def num_threads(threads: int) -> int:
    """pycolmap's thread count for ``threads``: as given when > 0, else the cores this process
    may run on (its CPU affinity, which sees a container's cpuset; pycolmap's own -1 counts every
    core of the host)."""
    if threads > 0:
        return threads
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise InputError(f"svolsdf calibrate needs pycolmap, which is not installed; install it "
                         f"with: {_INSTALL}") from None
    return pycolmap


def _earlier_calibration(scene: Path) -> dict[str, int | None] | None:
    """The files a calibration written before `svolsdf.io.replace` kept its record holds, from
    its calibration.json; None when ``scene`` is no calibration."""
    try:
        registered = json.loads((scene / "calibration.json").read_text())["registered"]
        names = [f"images/{n}" for n in registered if isinstance(n, str)]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return dict.fromkeys(["calibration.json", *names,
                          *(f"sparse/0/{n}.txt" for n in ("cameras", "images", "points3D"))])


SCENE_OUTPUT = OutputSpec(command="svolsdf calibrate",
                          names=frozenset({"images", "sparse", "calibration.json"}),
                          keeps=frozenset({"colmap_logs"}), earlier="an earlier calibration",
                          legacy=_earlier_calibration)
"""What `calibrate` writes (`svolsdf.io.replace`); COLMAP's log files are added to
SCENE/colmap_logs/ and kept, also when too few photos register."""


# --------------------------------------------------------------------------- SfM
def _run_sfm(pycolmap, work: Path, photos: list[Photo], single: bool, matcher: str,
             cfg: CalibrateConfig, timing: dict) -> Path | None:
    """Features, matching and mapping in ``work``; the largest model's text folder or None."""
    from tqdm import tqdm

    db = work / "database.db"
    images = work / "images"
    pycolmap.Database.open(db).close()
    mode = pycolmap.CameraMode.SINGLE if single else pycolmap.CameraMode.PER_IMAGE
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    names = [p.name for p in photos]
    t0 = time.perf_counter()
    # the images (and their shared camera) enter the database first; features are extracted in
    # batches afterwards so that the progress bar moves
    pycolmap.import_images(db, images, camera_mode=mode, image_names=names, options=reader)
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = num_threads(cfg.threads)
    ext.max_image_size = -1  # the inputs are already at max_size
    ext.sift.max_num_features = cfg.max_features
    batch = 8
    with tqdm(total=len(names), desc="calibrate: features", unit="photo",
              disable=not cfg.progress) as bar:
        for i in range(0, len(names), batch):
            pycolmap.extract_features(db, images, image_names=names[i:i + batch],
                                      camera_mode=mode, reader_options=reader,
                                      extraction_options=ext, device=pycolmap.Device.cpu)
            bar.update(len(names[i:i + batch]))
    timing["features"] = round(time.perf_counter() - t0, 2)

    t0 = time.perf_counter()
    mopt = pycolmap.FeatureMatchingOptions()
    mopt.num_threads = num_threads(cfg.threads)
    n_pairs = len(names) * (len(names) - 1) // 2
    log.info("calibrate: matching %s (%d photos%s)", matcher, len(names),
             f", {n_pairs} pairs" if matcher == "exhaustive" else "")
    with tqdm(total=1, desc=f"calibrate: matching ({matcher})", unit="step",
              disable=not cfg.progress) as bar:
        if matcher == "sequential":
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = 10
            pycolmap.match_sequential(db, matching_options=mopt, pairing_options=pairing,
                                      device=pycolmap.Device.cpu)
        else:
            pycolmap.match_exhaustive(db, matching_options=mopt, device=pycolmap.Device.cpu)
        bar.update()
    timing["matching"] = round(time.perf_counter() - t0, 2)

    t0 = time.perf_counter()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads(cfg.threads)
    opts.random_seed = cfg.seed
    opts.min_model_size = min(opts.min_model_size, cfg.min_registered)
    (work / "sparse").mkdir()
    with tqdm(total=len(names), desc="calibrate: mapping", unit="photo",
              disable=not cfg.progress) as bar:
        def _registered():
            bar.update()

        recs = pycolmap.incremental_mapping(db, images, work / "sparse", options=opts,
                                            initial_image_pair_callback=lambda: bar.update(2),
                                            next_image_callback=_registered)
    timing["mapping"] = round(time.perf_counter() - t0, 2)
    if not recs:
        return None
    best = max(recs.values(), key=lambda r: r.num_reg_images())
    out = work / "model"
    out.mkdir()
    best.write_text(str(out))
    return out


# --------------------------------------------------------------------------- undistortion
def _radial_scale(k: float, r2: np.ndarray) -> np.ndarray:
    return 1.0 + k * r2


def undistort_simple_radial(image: Image.Image, f: float, cx: float, cy: float,
                            k: float) -> Image.Image:
    """Resample a photo of a SIMPLE_RADIAL camera (f, cx, cy, k; COLMAP pixel convention, centre
    of the top-left pixel at (0.5, 0.5)) to the pinhole camera with the same f, cx, cy and size.

    Output pixel u looks up the photo at c + f * x (1 + k |x|^2), x = (u - c) / f (COLMAP's
    distortion model), bicubically; pixels that fall outside the photo repeat its border.
    """
    w, h = image.size
    u = (np.arange(w) + 0.5 - cx) / f
    v = (np.arange(h) + 0.5 - cy) / f
    x, y = np.meshgrid(u, v)
    s = _radial_scale(k, x * x + y * y)
    ud, vd = cx + f * x * s, cy + f * y * s
    grid = torch.from_numpy(np.stack([2 * ud / w - 1, 2 * vd / h - 1], -1)).float()[None]
    img = torch.from_numpy(np.asarray(image.convert("RGB"), dtype=np.float32)).permute(2, 0, 1)
    out = F.grid_sample(img[None], grid, mode="bicubic", padding_mode="border",
                        align_corners=False)[0]
    arr = out.clamp(0, 255).round().byte().permute(1, 2, 0).numpy()
    return Image.fromarray(arr)


def _undistort_points(xy: np.ndarray, f: float, cx: float, cy: float, k: float) -> np.ndarray:
    """(N, 2) distorted pixels -> the pinhole pixels of the same rays (fixed-point inversion)."""
    xd = (xy - [cx, cy]) / f
    x = xd.copy()
    for _ in range(20):
        x = xd / _radial_scale(k, (x * x).sum(-1, keepdims=True))
    return x * f + [cx, cy]


def _write_scene(model: Path, work: Path, scene: Path, cfg: CalibrateConfig) -> dict:
    """Undistort the model's images into SCENE/images and write SCENE/sparse/0 (text)."""
    from tqdm import tqdm

    cams = {}
    lines = []
    for ln in (model / "cameras.txt").read_text().splitlines():
        if ln.startswith("#") or not ln.strip():
            continue
        t = ln.split()
        cid, name, w, h, p = int(t[0]), t[1], int(t[2]), int(t[3]), [float(x) for x in t[4:]]
        if name == "SIMPLE_RADIAL":
            f, cx, cy, k = p
        elif name in ("SIMPLE_PINHOLE",):
            (f, cx, cy), k = p, 0.0
        else:
            raise RuntimeError(f"calibrate: unexpected camera model {name} from pycolmap")
        cams[cid] = (w, h, f, cx, cy, k)
        lines.append(f"{cid} PINHOLE {w} {h} {f!r} {f!r} {cx!r} {cy!r}")
    sparse = scene / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "\n".join(lines) + "\n")

    raw = [ln for ln in (model / "images.txt").read_text().splitlines()
           if not ln.startswith("#")]
    out_lines, names = [], []
    img_dir = scene / "images"
    img_dir.mkdir()
    i = 0
    pairs = []
    while i < len(raw):
        if not raw[i].strip():
            i += 1
            continue
        pairs.append((raw[i], raw[i + 1] if i + 1 < len(raw) else ""))
        i += 2
    for head, pts in tqdm(pairs, desc="calibrate: undistorting", unit="photo",
                          disable=not cfg.progress):
        t = head.split()
        cid, name = int(t[8]), " ".join(t[9:])
        w, h, f, cx, cy, k = cams[cid]
        names.append(name)
        tok = pts.split()
        if tok:
            a = np.array(tok, dtype=object).reshape(-1, 3)
            xy = _undistort_points(a[:, :2].astype(np.float64), f, cx, cy, k)
            pts = " ".join(f"{x:.4f} {y:.4f} {pid}" for (x, y), pid in zip(xy, a[:, 2],
                                                                           strict=True))
        out_lines += [head, pts]
        src = work / "images" / name
        # corner displacement below 0.05 px: the photo is used as it is
        r2 = max((cx / f) ** 2 + (cy / f) ** 2, ((w - cx) / f) ** 2 + ((h - cy) / f) ** 2)
        if abs(k) * r2 * np.sqrt(r2) * f < 0.05:
            shutil.copyfile(src, img_dir / name)
        else:
            with Image.open(src) as im:
                im.load()
                out = undistort_simple_radial(im, f, cx, cy, k)
            kw = {"quality": 95} if Path(name).suffix.lower() in (".jpg", ".jpeg") else {}
            out.save(img_dir / name, **kw)
    (sparse / "images.txt").write_text(
        "# Image list with two lines of data per image:\n"
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n" + "\n".join(out_lines) + "\n")
    shutil.copyfile(model / "points3D.txt", sparse / "points3D.txt")
    dist = {cid: c[5] for cid, c in cams.items()}
    return {"registered": names, "radial_distortion": dist,
            "focal_px": {cid: c[2] for cid, c in cams.items()}}


def _mean_reprojection_error(model: Path) -> float | None:
    errs = []
    for ln in (model / "points3D.txt").read_text().splitlines():
        if ln.startswith("#") or not ln.strip():
            continue
        errs.append(float(ln.split()[7]))
    return round(float(np.mean(errs)), 4) if errs else None


def _colmap_log_files(pycolmap, folder: Path | None) -> None:
    """Send COLMAP's log (glog) to files in ``folder`` and not to the terminal, where it would
    interleave with the progress bars; None writes no file (glog would start new ones in /tmp)
    and gives the terminal back its copy (pycolmap's default).

    glog names a file BASE + date + pid, one file per severity: each severity gets its own
    base (``colmap.WARNING.``), since one base for all made the second file's name the first's
    ("Could not create log file: File exists", "COULD NOT CREATE LOGFILE" in the terminal).
    """
    logging_ = pycolmap.logging
    if not hasattr(logging_, "set_log_destination"):  # pragma: no cover - older pycolmap
        return
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
    for level, name in ((logging_.INFO, "INFO"), (logging_.WARNING, "WARNING"),
                        (logging_.ERROR, "ERROR")):
        logging_.set_log_destination(level, "" if folder is None
                                     else str(folder / f"colmap.{name}."))
    logging_.alsologtostderr = folder is None


# --------------------------------------------------------------------------- entry point
def _calibrate_into(stage: Path, pycolmap, work: Path, inputs: Path, photos: list[Photo],
                    video: bool, single: bool, matcher: str, cfg: CalibrateConfig,
                    timing: dict, t_all: float) -> dict:
    """SfM on the prepared ``photos`` in ``work``; the scene and its summary written into
    ``stage`` (a new folder inside SCENE, swapped in by `replace_outputs`)."""
    scene = stage.parent
    # COLMAP logs every step at INFO level; keep its warnings and errors unless -v, in
    # SCENE/colmap_logs/ (its own default is a file per run in /tmp)
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if log.isEnabledFor(logging.DEBUG) else 1
    _colmap_log_files(pycolmap, scene / "colmap_logs")
    try:
        model = _run_sfm(pycolmap, work, photos, single, matcher, cfg, timing)
    finally:
        pycolmap.logging.minloglevel = level
        _colmap_log_files(pycolmap, None)
    n_reg = 0
    if model is not None:
        n_reg = sum(1 for ln in (model / "images.txt").read_text().splitlines()
                    if ln.strip() and not ln.startswith("#")) // 2
    if n_reg < cfg.min_registered:
        raise CalibrationError(
            f"{inputs}: only {n_reg} of {len(photos)} "
            f"{'frames' if video else 'photos'} could be registered (at least "
            f"{cfg.min_registered} needed). What helps: more overlap between neighbouring "
            f"photos (every part seen by 3 or more, 10-20 degrees apart), more photos, "
            f"sharp photos of a textured object, "
            + ("more --frames, " if video else "")
            + ("--matcher exhaustive" if matcher == "sequential" else
               "a larger --max-size"))
    t0 = time.perf_counter()
    written = _write_scene(model, work, stage, cfg)
    timing["write"] = round(time.perf_counter() - t0, 2)
    reg = set(written["registered"])
    timing["total"] = round(time.perf_counter() - t_all, 2)
    summary = {
        "inputs": str(inputs), "video": video, "num_inputs": len(photos),
        "size": list(photos[0].size), "shared_camera": single, "matcher": matcher,
        "registered": sorted(reg), "unregistered": [p.name for p in photos if p.name not in reg],
        "mean_reprojection_error_px": _mean_reprojection_error(model),
        "radial_distortion_removed": written["radial_distortion"],
        "focal_px": written["focal_px"],
        "sources": {p.name: p.source for p in photos},
        "seconds": timing, "config": asdict(cfg),
        "pycolmap": getattr(pycolmap, "__version__", "unknown"),
    }
    (stage / "calibration.json").write_text(json.dumps(summary, indent=1))
    return summary


def calibrate(inputs: str | Path, scene: str | Path, cfg: CalibrateConfig | None = None) -> dict:
    """Calibrate photos (a folder) or a video and write a COLMAP scene (module docstring).

    Args:
        inputs: a folder of photos or a video file.
        scene: the output scene folder: new, empty, or an earlier calibration, which is replaced
            only once the new one is complete (`svolsdf.io.replace`); it may hold the folder
            of the photos (SCENE/photos), not in SCENE/images, which it writes.
        cfg: options; default `CalibrateConfig()`.

    Returns:
        the summary written to SCENE/calibration.json: ``inputs``, ``registered`` (names),
        ``unregistered`` (names), ``shared_camera``, ``matcher``, ``seconds``, ...

    Raises:
        InputError: pycolmap (or, for a video, imageio-ffmpeg) is missing, unreadable photos,
            photos of different shapes, a bad option, or an output folder that holds files of
            the user's where the scene is written; raised before SCENE is touched.
        CalibrationError: fewer than ``cfg.min_registered`` photos registered.
    """
    cfg = cfg or CalibrateConfig()
    if cfg.matcher not in MATCHERS:
        raise InputError(f"--matcher: unknown matcher {cfg.matcher!r} ({', '.join(MATCHERS)})")
    if cfg.max_size is not None and cfg.max_size < 64:
        raise InputError(f"--max-size {cfg.max_size} is too small (at least 64 pixels)")
    pycolmap = _pycolmap()
    from svolsdf.io.paths import input_path

    # every input before SCENE is touched: the paths, then the photos themselves (read into a
    # work folder); an earlier calibration in SCENE is replaced only by a finished one
    inputs = input_path(inputs, "folder of photos or video file")
    scene = check_replace(scene, SCENE_OUTPUT, [inputs])
    t_all = time.perf_counter()
    timing: dict = {}
    with tempfile.TemporaryDirectory(prefix="svolsdf_calibrate_") as tmp:
        work = Path(tmp)
        t0 = time.perf_counter()
        photos, video = gather_inputs(inputs, work / "images", cfg.max_size, cfg.frames,
                                      progress=cfg.progress)
        timing["inputs"] = round(time.perf_counter() - t0, 2)
        if len(photos) < cfg.min_registered:
            raise InputError(f"{inputs}: {len(photos)} photo(s); calibration needs at least "
                             f"{cfg.min_registered} overlapping photos (better 10 or more)")
        single = shared_camera(photos, video)
        matcher = cfg.matcher if cfg.matcher != "auto" else ("sequential" if video
                                                             else "exhaustive")
        log.info("calibrate: %d %s at %dx%d, %s, %s matching", len(photos),
                 "frames" if video else "photos", *photos[0].size,
                 "one shared camera" if single else "one camera per photo", matcher)
        with replace_outputs(scene, SCENE_OUTPUT, [inputs]) as stage:
            summary = _calibrate_into(stage, pycolmap, work, inputs, photos, video, single,
                                      matcher, cfg, timing, t_all)
    if summary["unregistered"]:
        log.warning("calibrate: %d of %d photos were not registered: %s",
                    len(summary["unregistered"]), len(photos),
                    ", ".join(summary["unregistered"][:10]))
    return summary

