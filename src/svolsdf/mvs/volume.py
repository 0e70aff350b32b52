"""`ProbabilityVolume`: one reference view's depth distribution at one cascade stage."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from svolsdf.scene.cameras import Cameras

__all__ = ["ProbabilityVolume"]


@dataclass
class ProbabilityVolume:
    """Per-pixel depth hypotheses and their probabilities for one reference view and stage.

    Stage 1's fronto-parallel planes and stages 2-3's per-pixel ranges share this type
    (docs/architecture.md "Interfaces").

    Attributes:
        depths: (D, H, W) hypothesis z-depths in world units, increasing along D.
        prob: (D, H, W) probabilities, summing to 1 over D.
        depth: (H, W) the backbone's depth estimate: the expectation sum_k prob_k * depths_k
            (docs/method.md 2.4), or for the plane sweep by default the expectation around the most
            likely hypothesis (`svolsdf.mvs.backbone.mode_depth`).
        confidence: (H, W) photometric confidence in [0, 1] (docs/method.md 2.4, 4-bin sum).
        cameras: the reference camera (1 view) at the volume's resolution (W, H).
        view_id: the reference view id.
        stage: cascade stage, 1-based.
        inverse_depth: True when stage-1 planes are spaced uniformly in inverse depth
            (docs/method.md 2.5); the soft-consistency lookup (docs/method.md 3, step 6) follows it.
    """

    depths: Tensor
    prob: Tensor
    depth: Tensor
    confidence: Tensor
    cameras: Cameras
    view_id: int
    stage: int = 1
    inverse_depth: bool = False

    def __post_init__(self) -> None:
        if self.depths.ndim != 3 or self.prob.shape != self.depths.shape:
            raise ValueError(
                f"ProbabilityVolume: depths {tuple(self.depths.shape)} and prob "
                f"{tuple(self.prob.shape)} must both be (D, H, W)"
            )
        D, H, W = self.depths.shape
        if self.depth.shape != (H, W) or self.confidence.shape != (H, W):
            raise ValueError(
                f"ProbabilityVolume: depth {tuple(self.depth.shape)} and confidence "
                f"{tuple(self.confidence.shape)} must be (H, W) = ({H}, {W})"
            )
        if len(self.cameras) != 1 or (self.cameras.width, self.cameras.height) != (W, H):
            raise ValueError(
                f"ProbabilityVolume: camera must be one view at {W}x{H}, got "
                f"{len(self.cameras)} view(s) at {self.cameras.width}x{self.cameras.height}"
            )

    @property
    def num_depths(self) -> int:
        return self.depths.shape[0]

    def to(self, device=None) -> ProbabilityVolume:
        return ProbabilityVolume(
            self.depths.to(device), self.prob.to(device), self.depth.to(device),
            self.confidence.to(device), self.cameras.to(device), self.view_id, self.stage,
            self.inverse_depth,
        )

    def save(self, path) -> None:
        """Write a .npz (prob as float16) atomically, deflating only the arrays that shrink.

        Deflate took ~0.8 s of the ~1 s per stage-3 volume at 768x576 (scale 2: 8 x 1152 x 1536)
        for files 30 % smaller, and over a tenth of the MVS stages' time. Each array
        is now deflated (level 1) only when a sample of its bytes shrinks to under half
        (`_deflates_well`): stage 1's fronto-parallel ``depths`` (~200x) and stage 2's (~5x);
        the probabilities, the depth and confidence maps and stage 3's per-pixel hypotheses
        (0.5-0.8 of their size) are stored. The values written are the same; `numpy.load` reads
        either, and files written deflated throughout (before) still load.

        The file is written through the project's atomic writer
        (`svolsdf.io.runfolder.atomic_write`): a temporary name unique to the writer beside
        ``path``, renamed when complete, removed when the write fails.

        Args:
            path: the .npz file; its folder is created.

        Raises:
            InputError: the file cannot be written (a full disk, a read-only folder), naming it.
        """
        import zipfile

        import numpy as np

        from svolsdf.io.runfolder import atomic_write

        arrays = {
            "depths": self.depths.float().cpu().numpy(),
            "prob": self.prob.to(torch.float16).cpu().numpy(),
            "depth": self.depth.float().cpu().numpy(),
            "confidence": self.confidence.float().cpu().numpy(),
            "K": self.cameras.K[0].double().cpu().numpy(),
            "w2c": self.cameras.w2c[0].double().cpu().numpy(),
            "size": np.array([self.cameras.width, self.cameras.height]),
            "meta": np.array([self.view_id, self.stage, int(self.inverse_depth)]),
        }

        def write(tmp) -> None:
            with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as zf:
                for name, arr in arrays.items():
                    arr = np.ascontiguousarray(arr)
                    # ZipFile.open(name, "w") takes the archive's compression when it opens
                    zf.compression = (zipfile.ZIP_DEFLATED if _deflates_well(arr)
                                      else zipfile.ZIP_STORED)
                    zf.compresslevel = 1
                    with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                        np.lib.format.write_array(f, arr, allow_pickle=False)

        atomic_write(path, write, suffix=".npz")

    @classmethod
    def load(cls, path) -> ProbabilityVolume:
        """Read a volume written by :meth:`save`."""
        import numpy as np

        z = np.load(path)
        prob = torch.from_numpy(z["prob"].astype(np.float32))
        prob = prob / prob.sum(0, keepdim=True).clamp_min(1e-12)
        W, H = (int(v) for v in z["size"])
        cams = Cameras(
            torch.from_numpy(z["K"])[None].float(), torch.from_numpy(z["w2c"])[None].float(), W, H
        )
        view_id, stage, inv = (int(v) for v in z["meta"])
        return cls(
            torch.from_numpy(z["depths"]), prob, torch.from_numpy(z["depth"]),
            torch.from_numpy(z["confidence"]), cams, view_id, stage, bool(inv),
        )


def _deflates_well(arr, sample: int = 1 << 20, pieces: int = 4, ratio: float = 0.5) -> bool:
    """Whether deflate (level 1) shrinks ``arr``'s bytes to under ``ratio``, judged on
    ``pieces`` evenly spaced pieces of ``sample`` bytes in all (the whole array when smaller).

    Args:
        arr: a C-contiguous numpy array of any shape.

    Returns:
        True to deflate the array, False to store it.
    """
    import zlib

    import numpy as np

    raw = arr.reshape(-1).view(np.uint8)
    n = raw.size
    if n <= sample:
        data = raw.tobytes()
    else:
        step = sample // pieces
        starts = np.linspace(0, n - step, pieces).astype(np.int64)
        data = b"".join(raw[s:s + step].tobytes() for s in starts)
    return len(zlib.compress(data, 1)) < ratio * max(len(data), 1)
