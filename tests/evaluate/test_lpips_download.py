"""LPIPS without the team's folder: the lpips package's heads with torchvision's backbone,
fetched once into the torch cache and checked by SHA-256, or given as a local file. The download
is served here by a file server on localhost from a backbone the test makes (the shared weights'
``features``), so the distances must equal those of the shared weights."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch
from tests.io.file_server import serve

from conftest import shared_path
from svolsdf.errors import InputError
from svolsdf.evaluate import lpips as lp
from svolsdf.io.weights import PublishedWeights, sha256


@pytest.fixture
def served(tmp_path, monkeypatch):
    """A backbone file of the shared AlexNet weights served on localhost as torchvision's
    ``alex`` entry (BACKBONES patched to its URL and checksum); TORCH_HOME in tmp_path.
    Yields (the served file, the list of paths requested)."""
    full = torch.load(str(shared_path("weights", "lpips") / "alexnet_lpips_v0.1.pth"),
                      map_location="cpu", weights_only=True)
    root = tmp_path / "www"
    root.mkdir()
    f = root / "alexnet-test.pth"
    torch.save({k: v for k, v in full.items() if k.startswith("features.")}, f)
    with serve(root) as (base, asked):
        monkeypatch.setitem(lp.BACKBONES, "alex", PublishedWeights(
            "LPIPS-alex test backbone", "alexnet-test.pth", f"{base}/{f.name}", sha256(f),
            f.stat().st_size))
        monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
        monkeypatch.delenv(lp.BACKBONE_ENV, raising=False)
        yield f, asked


def _pair():
    g = torch.Generator().manual_seed(0)
    return (torch.rand(2, 3, 64, 64, generator=g) * 2 - 1,
            torch.rand(2, 3, 64, 64, generator=g) * 2 - 1)


def test_backbone_fetched_once_into_the_torch_cache_gives_the_shared_distances(served,
                                                                              monkeypatch,
                                                                              tmp_path):
    f, asked = served

    def no_shared_folder():
        raise InputError("no shared folder")

    monkeypatch.setattr(lp, "default_lpips_dir", no_shared_folder)
    model = lp.LPIPS("alex")  # no weights, no shared folder: the heads + the fetched backbone
    cached = tmp_path / "torch" / "hub" / "checkpoints" / "alexnet-test.pth"
    assert cached.is_file() and sha256(cached) == sha256(f)
    assert len([a for a in asked if "alexnet-test" in a]) == 1
    lp.LPIPS("alex")  # the second time from the cache: no request
    assert len([a for a in asked if "alexnet-test" in a]) == 1
    shared = lp.LPIPS("alex", shared_path("weights", "lpips"))
    x, y = _pair()
    torch.testing.assert_close(model(x, y), shared(x, y), rtol=0, atol=0)


def test_download_with_another_checksum_is_refused_and_not_kept(served, monkeypatch, tmp_path):
    spec = lp.BACKBONES["alex"]
    monkeypatch.setitem(lp.BACKBONES, "alex", replace(spec, sha256="0" * 64))
    with pytest.raises(InputError, match="SHA-256 .* not the published 0{64}; nothing was kept"):
        lp.backbone_file("alex", progress=False)
    folder = tmp_path / "torch" / "hub" / "checkpoints"
    assert list(folder.iterdir()) == []  # neither the file nor a temporary


def test_no_network_names_the_url_and_the_offline_ways(served, monkeypatch):
    spec = lp.BACKBONES["alex"]
    monkeypatch.setitem(lp.BACKBONES, "alex", replace(
        spec, url="http://127.0.0.1:9/alexnet-test.pth"))
    with pytest.raises(InputError, match=r"cannot download http://127.0.0.1:9/.*--lpips-weights"):
        lp.backbone_file("alex", progress=False)


def test_offline_backbone_file_by_option_or_environment_checked_by_sha256(served, monkeypatch,
                                                                         tmp_path):
    f, asked = served
    x, y = _pair()
    shared = lp.LPIPS("alex", shared_path("weights", "lpips"))
    by_option = lp.LPIPS("alex", f)  # --lpips-weights FILE: torchvision's file alone
    torch.testing.assert_close(by_option(x, y), shared(x, y), rtol=0, atol=0)
    monkeypatch.setenv(lp.BACKBONE_ENV, str(f))
    torch.testing.assert_close(lp.LPIPS("alex")(x, y), shared(x, y), rtol=0, atol=0)
    assert not asked  # nothing downloaded
    other = tmp_path / "other.pth"
    sd = torch.load(str(f), weights_only=True)
    sd["features.0.bias"] = sd["features.0.bias"] + 1
    torch.save(sd, other)
    with pytest.raises(InputError, match="not torchvision's alexnet-test.pth"):
        lp.LPIPS("alex", other)


@pytest.mark.parametrize("net, file", [("alex", "alexnet"), ("vgg", "vgg16")])
def test_shipped_heads_are_those_of_the_shared_weights(net, file):
    full = torch.load(str(shared_path("weights", "lpips") / f"{file}_lpips_v0.1.pth"),
                      map_location="cpu", weights_only=True)
    heads = lp._heads(net)
    assert sorted(heads) == [f"lin{k}.model.1.weight" for k in range(5)]
    for k, v in heads.items():
        assert torch.equal(v, full[k]), k
    assert Path(lp.__file__).with_name("lpips_heads").joinpath("LICENSE").is_file()
