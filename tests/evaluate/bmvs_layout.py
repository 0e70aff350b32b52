"""A synthetic scene written in the BlendedMVS layout, with exact ground truth: the fixture of
the BlendedMVS protocol's tests (tests/evaluate/test_blendedmvs.py, the function level, and
tests/evaluate/test_evaluate_blendedmvs.py, ``svolsdf evaluate --protocol blendedmvs``)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from svolsdf.io.ply import read_ply, write_points_ply
from svolsdf.scene.formats.mvsnet import write_cam_file
from svolsdf.scene.loaders import load_scene
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

MASKED = [0, 1, 3]
"""The views whose masks the layout's mask folder holds (BlendedMVS: the inputs and tests)."""


def write_bmvs_layout(root: Path, name: str = "bmvs_scan3", masked: list[int] = MASKED
                      ) -> tuple[Path, Path]:
    """(BlendedMVS-layout folder ROOT/NAME, IDR synthetic source ROOT/synth): a five-view 96x72
    synthetic scene (seed 7)'s cameras as cams/{id:08d}_cam.txt (world millimetres, z up, the
    table z = 0), its images as blended_images/, the masks of the views ``masked`` only."""
    src = make_synthetic_scene(root / "synth", SynthConfig(
        views=5, width=96, height=72, gt_points=6000, supersample=1, mesh_resolution=6.0,
        seed=7))
    s = load_scene(src, load_images=False)
    dst = root / name
    (dst / "cams").mkdir(parents=True)
    (dst / "blended_images").mkdir()
    (dst / "mask").mkdir()
    imgs = sorted((src / "image").iterdir())
    masks = sorted((src / "mask").iterdir())
    for k, vid in enumerate(s.view_ids):
        near, far = (float(x) for x in s.depth_range[k])
        write_cam_file(dst / "cams" / f"{vid:08d}_cam.txt", s.cameras.w2c[k].numpy(),
                       s.cameras.K[k].numpy(), near, (far - near) / 192, 192, far)
        shutil.copy(imgs[k], dst / "blended_images" / f"{vid:08d}.png")
        if vid in masked:
            shutil.copy(masks[k], dst / "mask" / f"{vid:08d}.png")
    return dst, src


def table_points(n: int = 4000, half: float = 300.0, seed: int = 0) -> np.ndarray:
    """(n, 3) points of the table top z = 0 (the synthetic scene's ground plane), |x|, |y| <
    ``half`` millimetres."""
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-half, half, (n, 2)), np.zeros(n)]


def write_ground_truth(src: Path, path: Path) -> np.ndarray:
    """The synthetic object's exact points with the table under it, as BlendedMVS' ground truth
    holds the ground: written to the PLY ``path``; returns them, (N, 3)."""
    gt = np.r_[read_ply(src / "gt_points.ply")["points"].astype(np.float64), table_points()]
    write_points_ply(path, gt)
    return gt
