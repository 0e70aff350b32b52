"""`ProbabilityVolume` files: the arrays deflated only where they shrink, the values unchanged,
files written deflated throughout (before issue 39) still read, and the writes atomic through the
project's writer (issue 50)."""

from __future__ import annotations

import errno
import re
import zipfile

import numpy as np
import pytest
import torch
from tests.mvs.synth import make_cameras

from svolsdf.errors import InputError
from svolsdf.mvs.volume import ProbabilityVolume, _deflates_well


def _volume(D=8, H=24, W=32, planes=True) -> ProbabilityVolume:
    g = torch.Generator().manual_seed(0)
    if planes:  # stage 1: fronto-parallel planes
        depths = torch.linspace(2.0, 6.0, D)[:, None, None].expand(D, H, W).contiguous()
    else:  # finer stages: per-pixel ranges
        depths = 4.0 + torch.rand(1, H, W, generator=g) + 0.01 * torch.arange(D)[:, None, None]
    prob = torch.softmax(torch.randn(D, H, W, generator=g), 0)
    cams = make_cameras(W, H)[0]
    return ProbabilityVolume(depths, prob, (prob * depths).sum(0), prob.max(0).values, cams,
                             view_id=3, stage=1 if planes else 3)


def _assert_same(a: ProbabilityVolume, b: ProbabilityVolume) -> None:
    for name in ("depths", "prob", "depth", "confidence"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert torch.equal(a.cameras.K, b.cameras.K) and torch.equal(a.cameras.w2c, b.cameras.w2c)
    assert (a.view_id, a.stage, a.inverse_depth) == (b.view_id, b.stage, b.inverse_depth)


def test_save_deflates_only_the_arrays_that_shrink(tmp_path):
    for planes in (True, False):
        v = _volume(planes=planes)
        v.save(tmp_path / "v.npz")
        with zipfile.ZipFile(tmp_path / "v.npz") as zf:
            kinds = {i.filename: i.compress_type for i in zf.infolist()}
        # planes compress ~100x; random probabilities do not
        assert kinds["depths.npy"] == (zipfile.ZIP_DEFLATED if planes else zipfile.ZIP_STORED)
        assert kinds["prob.npy"] == zipfile.ZIP_STORED
        back = ProbabilityVolume.load(tmp_path / "v.npz")
        assert torch.equal(back.depths, v.depths)
        assert torch.allclose(back.prob, v.prob, atol=1e-3)  # float16 on disk


def test_save_writes_a_temporary_of_its_own_and_renames_it(tmp_path, monkeypatch):
    """`svolsdf.io.runfolder.atomic_write`: while the file is written, the only new name in the
    folder is a temporary unique to this writer (``.v.npz.<pid>.<random>.tmp.npz``, not a fixed
    ``v.npz.tmp.npz`` that two writers would share), renamed to v.npz at the end."""
    seen = []
    real = np.lib.format.write_array

    def spy(f, arr, **kw):
        seen.append(sorted(p.name for p in tmp_path.iterdir()))
        return real(f, arr, **kw)

    monkeypatch.setattr(np.lib.format, "write_array", spy)
    v = _volume()
    v.save(tmp_path / "v.npz")
    assert seen and all(len(names) == 1 for names in seen), seen
    assert re.fullmatch(r"\.v\.npz\.\d+\.[0-9a-f]{8}\.tmp\.npz", seen[0][0]), seen[0]
    assert [p.name for p in tmp_path.iterdir()] == ["v.npz"]
    assert torch.allclose(ProbabilityVolume.load(tmp_path / "v.npz").prob, v.prob, atol=1e-3)


def test_a_full_disk_names_the_file_keeps_the_old_one_and_leaves_no_temporary(tmp_path,
                                                                               monkeypatch):
    v = _volume()
    v.save(tmp_path / "v.npz")
    before = (tmp_path / "v.npz").read_bytes()
    real, calls = np.lib.format.write_array, []

    def full(f, arr, **kw):
        calls.append(1)
        if len(calls) == 2:  # midway through the archive
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(f, arr, **kw)

    monkeypatch.setattr(np.lib.format, "write_array", full)
    with pytest.raises(InputError, match=r"v\.npz: cannot write it, the disk is full"):
        _volume(planes=False).save(tmp_path / "v.npz")
    assert [p.name for p in tmp_path.iterdir()] == ["v.npz"]
    assert (tmp_path / "v.npz").read_bytes() == before


def test_a_file_deflated_throughout_still_loads(tmp_path):
    """The format before: every array deflated (level 1); it reads as the new one."""
    v = _volume(planes=False)
    v.save(tmp_path / "new.npz")
    z = np.load(tmp_path / "new.npz")
    with zipfile.ZipFile(tmp_path / "old.npz", "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name in z.files:
            with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, z[name], allow_pickle=False)
    with zipfile.ZipFile(tmp_path / "old.npz") as zf:
        assert all(i.compress_type == zipfile.ZIP_DEFLATED for i in zf.infolist())
    _assert_same(ProbabilityVolume.load(tmp_path / "old.npz"),
                 ProbabilityVolume.load(tmp_path / "new.npz"))


def test_deflates_well_samples_large_arrays():
    assert _deflates_well(np.zeros((3, 1000, 1000), np.float32))
    rng = np.random.default_rng(0)
    assert not _deflates_well(rng.random((3, 1000, 1000), dtype=np.float32))
    assert not _deflates_well(np.array([1, 2, 3]))  # a few bytes grow
