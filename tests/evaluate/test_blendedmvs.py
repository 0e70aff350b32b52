"""The BlendedMVS protocol (svolsdf.evaluate.blendedmvs) on a synthetic scene written in the
BlendedMVS layout (cams/*_cam.txt, blended_images/, a mask folder with some views only), with
exact ground truth: the view lists, the partial mask folder, the ground plane's removal, the
masked and unmasked Chamfer and the relative improvement."""

from __future__ import annotations

import numpy as np
import pytest
from tests.evaluate.bmvs_layout import MASKED, table_points, write_bmvs_layout

from svolsdf.errors import InputError
from svolsdf.evaluate.blendedmvs import (
    above_plane,
    blendedmvs_chamfer,
    fit_ground_plane,
    inside_masks,
    protocol,
    relative_improvement,
)
from svolsdf.io.ply import read_ply
from svolsdf.scene.loaders import load_scene


@pytest.fixture(scope="module")
def bmvs(tmp_path_factory):
    """(BlendedMVS-layout folder, IDR synthetic source): `write_bmvs_layout`."""
    return write_bmvs_layout(tmp_path_factory.mktemp("bmvs"))


def test_protocol_lists_the_papers_views():
    p = protocol(1)
    assert p["inputs"] == [9, 10, 55] and len(p["test"]) == 12
    assert not set(p["inputs"]) & set(p["test"])
    assert all(len(protocol(k)["test"]) == 12 and len(protocol(k)["inputs"]) == 3
               for k in range(1, 10))
    with pytest.raises(InputError, match="scan 10"):
        protocol(10)


def test_a_partial_mask_folder_is_accepted_for_evaluation(bmvs):
    dst, _ = bmvs
    every = load_scene(dst, load_images=False)  # the views without masks: no masks in the run
    assert every.format == "mvsnet" and every.masks is None
    assert sorted(int(v) for v in every.extras["eval_mask_paths"]) == MASKED
    inputs = load_scene(dst, views=[0, 1, 3])  # every loaded view has one: the run uses them
    assert inputs.masks is not None and inputs.masks.shape[0] == 3


def test_ground_plane_masks_and_chamfer_on_exact_ground_truth(bmvs):
    dst, src = bmvs
    gt = read_ply(src / "gt_points.ply")["points"].astype(np.float64)
    scene = load_scene(dst, load_images=False)
    table = table_points()  # the table as ground-truth points, z = 0
    full = np.r_[gt, table]
    centre = scene.cameras.centers.numpy().mean(0)
    n, d = fit_ground_plane(full, centre, threshold=1.0)
    assert abs(abs(n[2]) - 1) < 1e-3 and abs(d) < 0.5 and n[2] > 0  # z = 0, facing up
    assert not above_plane(table, (n, d), margin=2.0).any()
    # a floater in front of view 0's corner, where its mask is empty
    K0, w2c0 = scene.cameras.K[0].numpy(), scene.cameras.w2c[0].numpy()
    depth = float(scene.depth_range[0].mean())
    cam_pt = np.linalg.solve(K0, [4.0, 4.0, 1.0]) * depth
    floater = (cam_pt - w2c0[:3, 3]) @ w2c0[:3, :3]  # camera -> world (R^T (x - t))
    # a prediction: the object shifted by 0.5 mm, plus the table and the floater
    pred = np.r_[gt + [0.5, 0, 0], table, floater[None]]
    res = blendedmvs_chamfer(pred, full, (n, d), margin=2.0, max_dist=20.0)
    u = res["unmasked"]
    assert u["n_gt"] < len(full) - 3900  # the table is removed from both
    assert 0.2 < u["accuracy"] < 0.6 and 0.2 < u["completeness"] < 0.6  # the shift, not the table
    # masked: the floater, outside the masks of the views 0, 1, 3 that see it, leaves
    ev = load_scene(dst, views=MASKED)
    m = {"K": ev.cameras.K.numpy(), "w2c": ev.cameras.w2c.numpy(),
         "masks": [x[0].numpy() > 0.5 for x in ev.masks]}
    assert not inside_masks(floater[None], **m)[0]
    assert inside_masks(gt, **m).mean() > 0.5  # the object stays (its rim: 96x72 masks)
    res = blendedmvs_chamfer(pred, full, (n, d), margin=2.0, max_dist=1e9, masked=m)
    assert res["masked"]["n_pred"] < res["unmasked"]["n_pred"]
    clean = blendedmvs_chamfer(pred[:-1], full, (n, d), margin=2.0, max_dist=1e9, masked=m)
    assert res["masked"] == clean["masked"]  # the floater is out of the masked score
    assert res["unmasked"]["accuracy"] > clean["unmasked"]["accuracy"]  # and in the other
    assert relative_improvement(0.8, 1.0) == pytest.approx(0.2)
    with pytest.raises(InputError):
        relative_improvement(1.0, 0.0)
