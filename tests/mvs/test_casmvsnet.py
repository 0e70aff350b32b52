"""CasMVSNet: checkpoint format (docs/method.md 2.1), chunked == unchunked, probabilities,
backbone."""

from __future__ import annotations

import pytest
import torch
from tests.mvs.synth import plane_scene

from svolsdf.errors import InputError
from svolsdf.mvs.backbone import get_backbone, photometric_confidence
from svolsdf.mvs.casmvsnet import CasMVSNetBackbone, mvs_input_size, stride_cameras
from svolsdf.mvs.casmvsnet_net import CasMVSNet, load_casmvsnet


# --------------------------------------------------------------------------- expected keys
def _bn(prefix: str, c: int) -> dict:
    return {
        f"{prefix}.bn.weight": (c,),
        f"{prefix}.bn.bias": (c,),
        f"{prefix}.bn.running_mean": (c,),
        f"{prefix}.bn.running_var": (c,),
        f"{prefix}.bn.num_batches_tracked": (),
    }


def _block(prefix: str, shape: tuple) -> dict:
    # ConvTranspose weights are (in, out, ...); the BN has "out" channels either way
    out = shape[1] if ".conv7" in prefix or ".conv9" in prefix or ".conv11" in prefix else shape[0]
    return {f"{prefix}.conv.weight": shape, **_bn(prefix, out)}


def official_keys() -> dict[str, tuple]:
    """The cascade-stereo CascadeMVSNet(fpn, cr_base_chs 8,8,8, share_cr False) state dict."""
    keys: dict[str, tuple] = {}
    feat = [
        ("conv0.0", (8, 3, 3, 3)), ("conv0.1", (8, 8, 3, 3)),
        ("conv1.0", (16, 8, 5, 5)), ("conv1.1", (16, 16, 3, 3)), ("conv1.2", (16, 16, 3, 3)),
        ("conv2.0", (32, 16, 5, 5)), ("conv2.1", (32, 32, 3, 3)), ("conv2.2", (32, 32, 3, 3)),
    ]
    for name, shape in feat:
        keys.update(_block(f"feature.{name}", shape))
    keys["feature.out1.weight"] = (32, 32, 1, 1)
    keys["feature.inner1.weight"] = (32, 16, 1, 1)
    keys["feature.inner1.bias"] = (32,)
    keys["feature.inner2.weight"] = (32, 8, 1, 1)
    keys["feature.inner2.bias"] = (32,)
    keys["feature.out2.weight"] = (16, 32, 3, 3)
    keys["feature.out3.weight"] = (8, 32, 3, 3)
    for i, cin in enumerate((32, 16, 8)):
        p = f"cost_regularization.{i}"
        k3 = (3, 3, 3)
        reg = [
            ("conv0", (8, cin, *k3)), ("conv1", (16, 8, *k3)), ("conv2", (16, 16, *k3)),
            ("conv3", (32, 16, *k3)), ("conv4", (32, 32, *k3)), ("conv5", (64, 32, *k3)),
            ("conv6", (64, 64, *k3)),
            ("conv7", (64, 32, *k3)), ("conv9", (32, 16, *k3)), ("conv11", (16, 8, *k3)),
        ]
        for name, shape in reg:
            keys.update(_block(f"{p}.{name}", shape))
        keys[f"{p}.prob.weight"] = (1, 8, *k3)
    return keys


def random_model(seed: int = 0) -> CasMVSNet:
    """Random weights and BatchNorm statistics (so BN is not the identity), eval mode."""
    g = torch.Generator().manual_seed(seed)
    m = CasMVSNet()
    with torch.no_grad():
        for mod in m.modules():
            if isinstance(mod, torch.nn.modules.batchnorm._BatchNorm):
                mod.running_mean.copy_(torch.rand(mod.num_features, generator=g) * 0.4 - 0.2)
                mod.running_var.copy_(torch.rand(mod.num_features, generator=g) * 1.5 + 0.5)
                mod.weight.copy_(torch.rand(mod.num_features, generator=g) + 0.5)
                mod.bias.copy_(torch.rand(mod.num_features, generator=g) * 0.4 - 0.2)
                mod.num_batches_tracked.fill_(1000)
    return m.eval()


@pytest.fixture(scope="module")
def model() -> CasMVSNet:
    return random_model()


@pytest.fixture(scope="module")
def scene():
    # 96x64 working size (a multiple of 32, as the network needs), no x2 upsampling in the tests
    s, _ = plane_scene(W=96, H=64)
    return s


def _backbone(model, **cfg) -> CasMVSNetBackbone:
    cfg = {"ndepths": (8, 8, 8), "x2_mvsres": False, **cfg}
    return CasMVSNetBackbone(model, **cfg)


# --------------------------------------------------------------------------- checkpoint format
def test_state_dict_keys_and_shapes_match_official():
    sd = CasMVSNet().state_dict()
    expected = official_keys()
    assert set(sd) == set(expected)
    assert {k: tuple(v.shape) for k, v in sd.items()} == expected
    assert len(sd) == 238


def test_save_reload_strict_gives_identical_outputs(tmp_path, model, scene):
    p = tmp_path / "casmvsnet.ckpt"
    torch.save({"epoch": 15, "model": model.state_dict()}, p)
    loaded = load_casmvsnet(p)
    assert not loaded.training
    a = _backbone(model).stage(1, scene, ref_ids=[0])[0]
    b = _backbone(loaded).stage(1, scene, ref_ids=[0])[0]
    assert torch.equal(a.prob, b.prob)
    assert torch.equal(a.depth, b.depth)


def test_dataparallel_prefix_is_stripped(tmp_path, model):
    p = tmp_path / "dp.ckpt"
    torch.save({"model": {f"module.{k}": v for k, v in model.state_dict().items()}}, p)
    loaded = load_casmvsnet(p)
    for k, v in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v)


def test_wrong_architecture_names_missing_and_unexpected_keys(tmp_path, model):
    sd = dict(model.state_dict())
    sd["cost_reg_0.conv0.conv.weight"] = sd.pop("cost_regularization.0.conv0.conv.weight")
    sd["toplayer.weight"] = torch.zeros(1)
    p = tmp_path / "other.ckpt"
    torch.save({"model": sd}, p)
    with pytest.raises(InputError) as e:
        load_casmvsnet(p)
    msg = str(e.value)
    assert str(p) in msg
    assert "missing" in msg and "cost_regularization.0.conv0.conv.weight" in msg
    assert "unexpected" in msg and "cost_reg_0.conv0.conv.weight" in msg
    assert "toplayer.weight" in msg


def test_wrong_shapes_and_bad_files(tmp_path, model):
    sd = dict(model.state_dict())
    sd["feature.out1.weight"] = torch.zeros(16, 32, 1, 1)
    p = tmp_path / "shape.ckpt"
    torch.save({"model": sd}, p)
    with pytest.raises(InputError, match=r"feature\.out1\.weight \(16, 32, 1, 1\)"):
        load_casmvsnet(p)
    with pytest.raises(InputError, match="nope.ckpt.*: CasMVSNet weights file does not exist"):
        load_casmvsnet(tmp_path / "nope.ckpt")
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="junk.ckpt"):
        load_casmvsnet(junk)
    torch.save({"optimizer": {}}, tmp_path / "nomodel.ckpt")
    with pytest.raises(InputError, match="'model'"):
        load_casmvsnet(tmp_path / "nomodel.ckpt")


def test_backbone_requires_weights(tmp_path):
    with pytest.raises(InputError, match="--weights"):
        get_backbone("casmvsnet")
    with pytest.raises(InputError, match="missing.ckpt.*does not exist"):
        get_backbone("casmvsnet", weights=tmp_path / "missing.ckpt")


def test_registry_loads_checkpoint(tmp_path, model, scene):
    """`get_backbone` loads the checkpoint's weights and options: the same volumes as the
    network it was saved from."""
    p = tmp_path / "c.ckpt"
    torch.save({"model": model.state_dict()}, p)
    bb = get_backbone("casmvsnet", weights=p, ndepths=(8, 8, 8), x2_mvsres=False)
    for k, v in model.state_dict().items():
        assert torch.equal(bb.model.state_dict()[k].cpu(), v.cpu()), k
    a = bb.stage(1, scene, ref_ids=[0])[0]
    b = _backbone(model).stage(1, scene, ref_ids=[0])[0]
    assert a.prob.shape[0] == 8 and torch.equal(a.prob, b.prob)


# --------------------------------------------------------------------------- chunking
def test_streamed_unet_equals_unchunked(model):
    reg = model.cost_regularization[2]
    c0 = torch.randn(1, 8, 16, 40, 24)
    with torch.no_grad():
        ref = reg.body(c0.clone())
        for budget in (1, 20_000):  # one or two rows per chunk, and a few rows per chunk
            out = reg.body_streamed(c0.clone(), budget)
            torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)


def test_chunked_stage_equals_unchunked(model):
    # 4 views of a 48-row stage-2-like volume; a budget so small that every chunk is 1-2 rows
    g = torch.Generator().manual_seed(1)
    V, C, H, W, D = 3, 16, 48, 24, 8
    feats = torch.randn(V, C, H, W, generator=g)
    s, _ = plane_scene(W=W, H=H)
    projs = s.cameras.proj.float()
    depths = (torch.linspace(3.5, 4.8, D)[:, None, None]
              + 0.05 * torch.randn(1, H, W, generator=g)).contiguous()
    ref = model.regularize(2, feats, projs, depths, chunk_mb=None)
    for mb in (1e-4, 0.05):
        out = model.regularize(2, feats, projs, depths, chunk_mb=mb)
        torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)


def test_cost_volume_rows_equal_full_volume(model):
    g = torch.Generator().manual_seed(2)
    s, _ = plane_scene(W=20, H=16)
    feats = torch.randn(3, 8, 16, 20, generator=g)
    depths = torch.linspace(3.0, 5.0, 8)[:, None, None].expand(8, 16, 20)
    full = model.cost_volume_rows(feats, s.cameras.proj.float(), depths, 0, 16)
    part = model.cost_volume_rows(feats, s.cameras.proj.float(), depths, 5, 11)
    torch.testing.assert_close(part, full[..., 5:11, :], rtol=1e-4, atol=1e-4)
    # variance of identical features is zero
    same = model.cost_volume_rows(feats[:1].expand(3, -1, -1, -1), torch.eye(4).expand(3, 4, 4),
                                  torch.ones(8, 16, 20), 0, 16, align_corners_quirk=False)
    assert same.abs().max() < 1e-5


# --------------------------------------------------------------------------- probabilities
def test_confidence_formula_on_hand_made_volume():
    # docs/method.md 2.4: s4_k = P_{k-1} + P_k + P_{k+1} + P_{k+2}; k* = floor(sum_k P_k k)
    p = torch.tensor([0.1, 0.2, 0.4, 0.2, 0.05, 0.05, 0.0, 0.0])
    kstar = int((p * torch.arange(8.0)).sum().floor())  # 2.15 -> 2
    assert kstar == 2
    expected = p[1] + p[2] + p[3] + p[4]
    conf = photometric_confidence(p.view(8, 1, 1).expand(8, 2, 3))
    torch.testing.assert_close(conf, expected.expand(2, 3))
    # at the first bin the sum is zero padded below: k* = 0 -> P_0 + P_1 + P_2
    q = torch.tensor([0.7, 0.2, 0.05, 0.05, 0, 0, 0, 0])
    torch.testing.assert_close(photometric_confidence(q.view(8, 1, 1))[0, 0], q[:3].sum())


def test_three_stages_probabilities_cameras_and_guide(model, scene):
    bb = _backbone(model)
    v1 = bb.stage(1, scene)
    assert [v.view_id for v in v1] == scene.view_ids
    assert v1[0].prob.shape == (8, 16, 24)
    torch.testing.assert_close(v1[0].prob.sum(0), torch.ones(16, 24))
    near, far = scene.depth_range[0].tolist()
    assert v1[0].depths[0].min() == pytest.approx(near)
    assert v1[0].depths[-1].max() == pytest.approx(far)
    assert ((v1[0].depth >= near) & (v1[0].depth <= far)).all()
    # stage-1 camera: K[:2] / 4 at a quarter of the size (docs/method.md 1.3)
    K = scene.cameras.K[0].float().clone()
    K[:2] /= 4
    torch.testing.assert_close(v1[0].cameras.K[0], K)
    # stage 2 from a constant guide: hypotheses centred on it, width D r Δ̄ (released r = 0.5)
    guide = {vid: torch.full((7, 9), 4.0) for vid in scene.view_ids}
    v2 = bb.stage(2, scene, ref_ids=[1], guide_depth=guide)[0]
    assert v2.prob.shape == (8, 32, 48) and v2.view_id == 1 and v2.stage == 2
    torch.testing.assert_close(v2.depths.mean(0), torch.full((32, 48), 4.0))
    dbar = (far - near) / 192
    width = float(v2.depths[-1, 0, 0] - v2.depths[0, 0, 0])
    assert width == pytest.approx(8 * 0.5 * dbar, rel=1e-4)  # from d - D r Δ̄/2 to d + D r Δ̄/2
    torch.testing.assert_close(v2.prob.sum(0), torch.ones(32, 48))
    # stage 3 from the previous volume, at the network input (= working) size
    v3 = bb.stage(3, scene, ref_ids=[1], prev={1: v2})[0]
    assert v3.prob.shape == (8, 64, 96) and (v3.cameras.width, v3.cameras.height) == (96, 64)
    assert torch.isfinite(v3.confidence).all() and (v3.confidence <= 1 + 1e-6).all()
    with pytest.raises(ValueError, match="guide depth"):
        bb.stage(3, scene, ref_ids=[1])


def test_mvs_input_size_and_stride_cameras(scene):
    assert mvs_input_size(768, 576) == (1536, 1152)  # docs/method.md 1.3 x2_mvsres
    assert mvs_input_size(768, 576, x2_mvsres=False) == (768, 576)
    assert mvs_input_size(800, 600) == (1600, 1216)
    c = stride_cameras(scene.cameras, 2)
    assert (c.width, c.height) == (48, 32)
    torch.testing.assert_close(c.K[:, 0, 2], scene.cameras.K[:, 0, 2] / 2)


def test_bad_depth_range_names_the_view(model, scene):
    bad = scene.select(scene.view_ids)
    bad.depth_range = bad.depth_range.clone()
    bad.depth_range[2] = torch.tensor([5.0, 5.0], dtype=torch.float64)
    with pytest.raises(InputError, match="view 2"):
        _backbone(model).stage(1, bad)


def test_casmvsnet_runs_at_the_mid_resolutions_scale(model, scene):
    """``mvs.scale`` 4/3 (the paper's mid resolution: the field at 864x1152, the network at
    1152x1536) is accepted and runs the network at that size; 1 and 2 stay x2_mvsres."""
    from svolsdf.config import preset
    from svolsdf.mvs.backbone import backbone_options, backbone_scale_problem

    assert mvs_input_size(1152, 864, scale=4 / 3) == (1536, 1152)
    assert backbone_scale_problem("casmvsnet", 4 / 3) is None
    c = preset("fast")
    c.mvs.backbone, c.mvs.scale = "casmvsnet", 4 / 3
    kw = backbone_options("casmvsnet", c.mvs)
    assert kw["scale"] == pytest.approx(4 / 3) and kw["x2_mvsres"] is False
    c.mvs.scale = 2.0
    assert "scale" not in backbone_options("casmvsnet", c.mvs)
    bb = _backbone(model, scale=4 / 3)  # 96x64 -> 128x85, rounded to 128x96
    v3 = bb.stage(3, scene, ref_ids=[1], prev={1: bb.stage(2, scene, ref_ids=[1], prev={
        1: bb.stage(1, scene, ref_ids=[1])[0]})[0]})[0]
    assert (v3.cameras.width, v3.cameras.height) == (128, 96)
