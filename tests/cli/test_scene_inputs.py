"""Scenes and options that were read silently wrong, failed late with a traceback, or were
refused with the wrong cause. One row per case; every command that loads a scene (reconstruct,
mvs, info) refuses each with exit status 2 and one line that names the file or the option and
the cause, before any stage runs: the stages are replaced by stand-ins that fail the test when
reached, and the output folder must not exist afterwards.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from svolsdf.cli import main
from svolsdf.scene.loaders import load_scene
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

COMMANDS = ("reconstruct", "mvs", "info")


# --------------------------------------------------------------------------- the scenes
def _colmap_from(idr: Path, root: Path) -> None:
    """``idr``'s views as a COLMAP text model (PINHOLE, no points) with images/."""
    s = load_scene(idr, load_images=False)
    sp = root / "sparse" / "0"
    sp.mkdir(parents=True)
    shutil.copytree(idr / "image", root / "images")
    K, w2c = s.cameras.K.double().numpy(), s.cameras.w2c.double().numpy()
    cams, imgs = [], []
    for i, p in enumerate(s.image_paths):
        f = [float(K[i][0, 0]), float(K[i][1, 1]), float(K[i][0, 2]) + 0.5,
             float(K[i][1, 2]) + 0.5]  # COLMAP's pixel centres at +0.5
        cams.append(f"{i + 1} PINHOLE {s.width} {s.height} " + " ".join(map(repr, f)))
        x, y, z, w = (float(v) for v in Rotation.from_matrix(w2c[i][:3, :3]).as_quat())
        t = " ".join(repr(float(v)) for v in w2c[i][:3, 3])
        imgs += [f"{i + 1} {w!r} {x!r} {y!r} {z!r} {t} {i + 1} {p.name}", ""]
    (sp / "cameras.txt").write_text("\n".join(cams) + "\n")
    (sp / "images.txt").write_text("\n".join(imgs) + "\n")
    (sp / "points3D.txt").write_text("")


def _nerf_from(idr: Path, root: Path) -> None:
    """``idr``'s views as a transforms.json (OpenGL camera-to-world, fl_x/fl_y/cx/cy)."""
    s = load_scene(idr, load_images=False)
    shutil.copytree(idr / "image", root / "image")
    K, w2c = s.cameras.K.double().numpy(), s.cameras.w2c.double().numpy()
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    frames = [{"file_path": f"image/{p.stem}", "transform_matrix": (np.linalg.inv(w2c[i]) @ flip
                                                                    ).tolist(),
               "fl_x": float(K[i][0, 0]), "fl_y": float(K[i][1, 1]),
               "cx": float(K[i][0, 2]) + 0.5, "cy": float(K[i][1, 2]) + 0.5}
              for i, p in enumerate(s.image_paths)]
    (root / "transforms.json").write_text(json.dumps({"w": s.width, "h": s.height,
                                                      "frames": frames}))


@pytest.fixture(scope="module")
def bases(tmp_path_factory):
    """A tiny synthetic scene (IDR layout, 3 views, 64x48) and the same views as a COLMAP and
    a NeRF scene."""
    base = tmp_path_factory.mktemp("inputs")
    idr = base / "idr"
    make_synthetic_scene(idr, SynthConfig(views=3, width=64, height=48, seed=2, supersample=1,
                                          gt_points=2000))
    _colmap_from(idr, base / "colmap")
    _nerf_from(idr, base / "nerf")
    return base


# --------------------------------------------------------------------------- the edits
def _rename(a: str, b: str) -> Callable[[Path], None]:
    return lambda s: (s / a).rename(s / b)


def _add_image(s: Path) -> None:
    shutil.copy(s / "image" / "000002.png", s / "image" / "000003.png")


def _resize_images(s: Path) -> None:  # cameras for 64x48, images a third of that
    for p in [*(s / "image").iterdir(), *(s / "mask").iterdir()]:
        Image.open(p).resize((24, 18)).save(p)


def _world_mat(fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[Path], None]:
    def edit(s: Path) -> None:
        d = dict(np.load(s / "cameras.npz"))
        d["world_mat_1"] = fn(d["world_mat_1"])
        np.savez(s / "cameras.npz", **d)
    return edit


def _camera_line(k: int, fn: Callable[[list[str]], list[str]]) -> Callable[[Path], None]:
    def edit(s: Path) -> None:
        f = s / "sparse" / "0" / "cameras.txt"
        lines = f.read_text().splitlines()
        lines[k] = " ".join(fn(lines[k].split()))
        f.write_text("\n".join(lines) + "\n")
    return edit


def _transforms(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    def edit(s: Path) -> None:
        f = s / "transforms.json"
        meta = json.loads(f.read_text())
        fn(meta)
        f.write_text(json.dumps(meta))
    return edit


def _angle_zero(meta: dict) -> None:
    for fr in meta["frames"]:
        for k in ("fl_x", "fl_y"):
            fr.pop(k)
    meta["camera_angle_x"] = 0


def _image_is_folder(s: Path) -> None:
    (s / "image" / "000001.png").unlink()
    (s / "image" / "000001.png").mkdir()


def _image_dangling(s: Path) -> None:
    (s / "image" / "000001.png").unlink()
    (s / "image" / "000001.png").symlink_to(s / "gone" / "000001.png")


def _gif(s: Path) -> None:
    for p in list((s / "image").iterdir()):
        Image.open(p).save(p.with_suffix(".gif"))
        p.unlink()


def _one_view(s: Path) -> None:
    d = dict(np.load(s / "cameras.npz"))
    np.savez(s / "cameras.npz", **{k: v for k, v in d.items() if k.endswith("_0")})
    for sub, n in (("image", 6), ("mask", 3)):
        for i in (1, 2):
            (s / sub / f"{i:0{n}d}.png").unlink()
    (s / "pair.txt").unlink()


@dataclass(frozen=True)
class Case:
    """One bad input.

    Attributes:
        name: the test's id.
        base: the scene it edits: idr, colmap or nerf.
        edit: (the scene's copy) -> None, makes the case.
        words: what the one line must hold ("{scene}" is the scene folder).
        commands: the commands it applies to.
        options: more arguments for reconstruct.
    """

    name: str
    base: str
    edit: Callable[[Path], None] | None
    words: tuple[str, ...]
    commands: tuple[str, ...] = COMMANDS
    options: tuple[str, ...] = ()


CASES = [
    # images matched to cameras by position
    Case("idr image renamed", "idr", _rename("image/000001.png", "image/000007.png"),
         ("{scene}/image/000007.png is view 7", "world_mat", "no image of view 1")),
    Case("idr extra image", "idr", _add_image,
         ("{scene}/image/000003.png is view 3", "which has no camera")),
    Case("idr mask renamed", "idr", _rename("mask/001.png", "mask/009.png"),
         ("{scene}/mask/009.png is view 9", "no mask of view 1")),
    # COLMAP models read as pinholes, or not found
    Case("colmap fisheye", "colmap",
         _camera_line(0, lambda t: [t[0], "OPENCV_FISHEYE", *t[2:], "0", "0", "0", "0"]),
         ("{scene}/sparse/0/cameras.txt", "OPENCV_FISHEYE", "supported: SIMPLE_PINHOLE")),
    Case("colmap unknown model", "colmap", _camera_line(1, lambda t: [t[0], "WEIRD", *t[2:]]),
         ("{scene}/sparse/0/cameras.txt", "WEIRD", "unknown model", "supported:")),
    Case("colmap pinhole with 2 parameters", "colmap", _camera_line(2, lambda t: t[:6]),
         ("{scene}/sparse/0/cameras.txt", "camera 3 (PINHOLE) has 2 parameters")),
    Case("colmap without images.txt", "colmap",
         lambda s: (s / "sparse" / "0" / "images.txt").unlink(),
         ("{scene}/sparse/0/images.txt is missing",)),
    # late failures
    Case("images do not fit their cameras", "idr", _resize_images,
         ("{scene}/image/000000.png is 24x18", "world_mat_0", "principal point")),
    Case("world_mat stored as a string", "idr", _world_mat(lambda P: np.array(str(P.tolist()))),
         ("{scene}/cameras.npz", "world_mat_1", "not as numbers")),
    Case("nerf camera_angle_x 0", "nerf", _transforms(_angle_zero),
         ("{scene}/transforms.json", "camera_angle_x is 0", "between 0 and pi")),
    Case("nerf frames of numbers", "nerf", _transforms(lambda m: m.update(frames=[1, 2, 3])),
         ("{scene}/transforms.json: frames[0] is 1, not an object",)),
    # the wrong cause
    Case("image that is a folder", "idr", _image_is_folder,
         ("{scene}/image/000001.png is a folder",)),
    Case("image that is a dangling link", "idr", _image_dangling,
         ("{scene}/image/000001.png is a symbolic link", "which does not exist")),
    Case("gif images", "idr", _gif,
         ("{scene}/image: no images found", ".gif", "accepted types: .bmp")),
    Case("views auto on one view", "idr", _one_view,
         ("{scene}: --views auto", "only 1 view"), commands=("reconstruct",),
         options=("--views", "auto")),
    # options that cannot fit in memory
    Case("grid resolution beyond memory", "idr", None,
         ("--set field.grid_resolution=100000", "memory"), commands=("reconstruct",),
         options=("--set", "field.grid_resolution=100000")),
    Case("mvs depths beyond memory", "idr", None,
         ("--set mvs.ndepths=[100000000, 32, 8]", "memory"), commands=("reconstruct",),
         options=("--set", "mvs.ndepths=[100000000,32,8]")),
]


def _argv(command: str, scene: Path, out: Path, case: Case) -> list[str]:
    if command == "info":
        return ["info", str(scene)]
    if command == "mvs":
        return ["mvs", str(scene), "-o", str(out)]
    return ["reconstruct", str(scene), "-o", str(out), "--no-progress", *case.options]


def _no_stage(mp: pytest.MonkeyPatch) -> None:
    """Every stage of reconstruct and the work of mvs fail the test when reached."""
    import svolsdf.commands.mvs as mvs
    from svolsdf.pipeline import Pipeline

    def reached(*a, **k):
        raise AssertionError("a stage ran")

    for name in dir(Pipeline):
        if name.startswith("stage_"):
            mp.setattr(Pipeline, name, reached)
    mp.setattr(mvs, "run_mvs", reached)


ROWS = [(c, cmd) for c in CASES for cmd in c.commands]


@pytest.mark.parametrize(("case", "command"), ROWS,
                         ids=[f"{c.name} ({cmd})" for c, cmd in ROWS])
def test_bad_input_is_refused_in_one_line_before_any_stage(case, command, bases, tmp_path,
                                                           capsys, monkeypatch):
    scene = tmp_path / "scene"
    shutil.copytree(bases / case.base, scene, symlinks=True)
    if case.edit is not None:
        case.edit(scene)
    out = tmp_path / "out"
    _no_stage(monkeypatch)
    try:
        main(_argv(command, scene, out, case))
        code = 0
    except SystemExit as e:
        code = e.code
    err = capsys.readouterr().err
    where = f"{case.name} ({command}): exit {code}\n{err}"
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), where
    for w in case.words:
        assert w.format(scene=scene) in lines[0], where
    assert not out.exists(), where


# --------------------------------------------------------------------------- read, not refused
def test_a_projection_matrix_of_any_scale_is_the_same_camera(bases, tmp_path):
    """world_mat_1 x 1e300 is the camera world_mat_1 (P is defined up to scale): read as it,
    not an overflow."""
    scene = tmp_path / "scene"
    shutil.copytree(bases / "idr", scene)
    _world_mat(lambda P: P * 1e300)(scene)
    a = load_scene(scene, load_images=False).cameras
    b = load_scene(bases / "idr", load_images=False).cameras
    torch.testing.assert_close(a.K, b.K)
    torch.testing.assert_close(a.w2c, b.w2c)


def test_images_are_matched_to_cameras_by_number_not_position(bases, tmp_path):
    """Names whose sorted order is not the cameras' (``0.png``, ``02.png``, ``1.png``, as
    unpadded or mixed numbering sorts): each image and mask goes with the camera its number
    names."""
    scene = tmp_path / "scene"
    shutil.copytree(bases / "idr", scene)
    ref = load_scene(bases / "idr")
    names = ["0.png", "1.png", "02.png"]
    for i, n in enumerate(names):
        (scene / "image" / f"{i:06d}.png").rename(scene / "image" / n)
        (scene / "mask" / f"{i:03d}.png").rename(scene / "mask" / n)
    s = load_scene(scene)
    torch.testing.assert_close(s.images, ref.images)
    torch.testing.assert_close(s.masks, ref.masks)
    assert [p.name for p in s.image_paths] == names


# --------------------------------------------------------------------------- messages elsewhere
def test_a_run_folder_without_views_json_names_that_file(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("scene:\n  path: somewhere\n")
    with pytest.raises(SystemExit) as e:
        main(["render", str(run)])
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and len(err.splitlines()) == 1, err
    assert "views.json missing" in err and "config.yaml" not in err.split("(")[1], err


def test_ctrl_c_while_the_command_imports_torch_exits_130_in_one_line(tmp_path):
    """Ctrl-C at startup, while the modules of the commands import torch (seconds)."""
    script = tmp_path / "stop.py"
    script.write_text(
        "import sys\n"
        "class Stop:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'torch':\n"
        "            raise KeyboardInterrupt\n"
        "sys.meta_path.insert(0, Stop())\n"
        "sys.argv = ['svolsdf', 'info', '.']\n"
        "from svolsdf.cli import main\n"
        "main()\n")
    src = Path(__file__).resolve().parents[2] / "src"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(src), os.environ.get(
        "PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env,
                       timeout=120)
    assert r.returncode == 130, r.stderr
    assert r.stderr.strip() == "interrupted", r.stderr
