"""PatchmatchNet without the team's folder: the authors' published module fetched once into the
torch cache, its SHA-256 the one documented (served here on localhost from the shared copy:
this machine has no internet); --weights FILE for a local file."""

from __future__ import annotations

from dataclasses import replace

import pytest
from tests.io.file_server import serve

from conftest import shared_path
from svolsdf.errors import InputError
from svolsdf.mvs import adapters
from svolsdf.mvs.backbone import get_backbone


@pytest.fixture
def published(tmp_path, monkeypatch):
    """The shared PatchmatchNet module served as the published one; no shared folder found;
    TORCH_HOME in tmp_path. Yields the paths requested."""
    f = shared_path("weights", "patchmatchnet", "patchmatchnet_dtu_module.pt")
    monkeypatch.setattr(adapters, "default_patchmatchnet_weights", lambda: None)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    with serve(f.parent) as (base, asked):
        monkeypatch.setattr(adapters, "PATCHMATCHNET",
                            replace(adapters.PATCHMATCHNET, url=f"{base}/{f.name}"))
        yield asked


def test_patchmatchnet_fetched_once_into_the_torch_cache(published, tmp_path):
    bb = get_backbone("patchmatchnet")  # no --weights, no shared folder
    assert isinstance(bb, adapters.PatchmatchNetBackbone)
    cached = tmp_path / "torch" / "hub" / "checkpoints" / adapters.PATCHMATCHNET.file
    assert cached.is_file()  # kept: the shared copy has the documented SHA-256 and size
    get_backbone("patchmatchnet")
    assert len(published) == 1  # the second time from the cache


def test_patchmatchnet_download_of_another_file_is_refused(published, monkeypatch, tmp_path):
    monkeypatch.setattr(adapters, "PATCHMATCHNET",
                        replace(adapters.PATCHMATCHNET, sha256="f" * 64))
    with pytest.raises(InputError, match="not the published f{64}; nothing was kept"):
        get_backbone("patchmatchnet")
    assert list((tmp_path / "torch" / "hub" / "checkpoints").iterdir()) == []


def test_patchmatchnet_without_network_names_the_address_and_weights(monkeypatch, tmp_path):
    monkeypatch.setattr(adapters, "default_patchmatchnet_weights", lambda: None)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setattr(adapters, "PATCHMATCHNET", replace(
        adapters.PATCHMATCHNET, url="http://127.0.0.1:9/module_000007.pt"))
    with pytest.raises(InputError, match=r"cannot download http://127.0.0.1:9/.*--weights FILE"):
        get_backbone("patchmatchnet")
