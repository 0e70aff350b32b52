"""The scene-format registry (`svolsdf.scene.formats`): the built-in formats keep their
detection order, titles and the message of a folder no format reads; a format registered here,
in the test file alone, is detected and loaded by `load_scene`."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from svolsdf.errors import InputError
from svolsdf.scene.formats import (
    SceneSource,
    get_scene_format,
    register_scene_format,
    scene_formats,
)
from svolsdf.scene.info import describe_scene
from svolsdf.scene.loaders import detect_format, load_scene
from svolsdf.scene.scene import SceneError
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

POINTER = "test_scene_pointer.txt"


def _is_pointer(path: Path) -> bool:
    return (path / POINTER).is_file()


@register_scene_format("test-pointer", _is_pointer, order=100,
                       looks_for=f"{POINTER} (a test's pointer to an IDR scene)",
                       title="a test's pointer")
def _read_pointer(path: Path, lighting=None) -> SceneSource:
    """The IDR scene whose folder the pointer file names, as this format."""
    target = Path((path / POINTER).read_text().strip())
    src = get_scene_format("idr").read(target, lighting=lighting)
    return dataclasses.replace(src, format="test-pointer", path=path)


def test_builtin_formats_keep_their_detection_order():
    names = [f.name for f in scene_formats()]
    assert names[:5] == ["idr", "dtu_raw", "mvsnet", "colmap", "nerf"]
    assert names.index("test-pointer") == len(names) - 1  # order 100: after the built-in ones
    assert get_scene_format("nerf").title == "NeRF transforms.json"
    with pytest.raises(InputError, match="unknown scene format 'nope'"):
        get_scene_format("nope")


def test_a_folder_no_format_reads_lists_what_each_looks_for(tmp_path):
    with pytest.raises(SceneError) as e:
        detect_format(tmp_path)
    assert str(e.value) == (
        f"{tmp_path}: no known scene layout found (looked for cameras.npz or cameras_sphere.npz "
        "with image/ or images/ (IDR/VolSDF/NeuS); Rectified/scanN/ with Calibration/cal18/ "
        "(DTU raw); cams/*_cam.txt with images/ or blended_images/ (MVSNet/BlendedMVS); "
        "sparse/0/ or sparse/ with cameras, images, points3D (.txt or .bin) and images/ "
        f"(COLMAP); transforms.json (NeRF); {POINTER} (a test's pointer to an IDR scene))")


def test_a_registered_format_is_detected_and_loaded(tmp_path):
    real = make_synthetic_scene(tmp_path / "real", SynthConfig(views=3, width=64, height=48,
                                                               supersample=1, gt_points=1000))
    folder = tmp_path / "pointer"
    folder.mkdir()
    (folder / POINTER).write_text(str(real))
    assert detect_format(folder) == "test-pointer"
    scene = load_scene(folder)
    ref = load_scene(real)
    assert scene.format == "test-pointer" and scene.view_ids == ref.view_ids
    assert (scene.images == ref.images).all()
    assert "format       test-pointer: a test's pointer" in describe_scene(scene)
