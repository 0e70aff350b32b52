"""A CPU-side detector of operations that force a device-host synchronisation on CUDA.

No GPU is needed: a `torch.overrides.TorchFunctionMode` sees every torch function and Tensor
method called from Python and records the ones that, on a CUDA tensor, make the host wait for
the device. The list follows ``torch.cuda.set_sync_debug_mode`` (which flags the same ops on a
GPU, pytorch/pytorch#62092) and the known cases collected in pytorch/pytorch#108968, #12461:

- a device value read on the host: ``item``, ``tolist``, ``numpy``, ``cpu``,
  ``__bool__``/``__int__``/``__float__``/``__index__``/``__format__``/``__repr__``
  (``if t:``, ``int(t)``, ``float(t)``, ``range(t)``, f-strings, logging), ``torch.equal``,
  ``allclose``;
- data-dependent output sizes: ``nonzero``, ``argwhere``, one-argument ``torch.where``,
  ``masked_select``, ``unique``/``unique_consecutive``, ``bincount``, ``histc``,
  ``repeat_interleave`` with tensor repeats and no ``output_size``, boolean-mask indexing
  (``t[mask]`` and ``t[mask] = v``, which go through ``nonzero``), indexing with a 0-dim
  tensor (pytorch/pytorch#105641);
- value checks on the host: ``multinomial`` (argument checks; #108968), ``normal`` with a
  tensor std, ``quantile``/``nanquantile`` with a tensor q, ``nanmedian``;
- host data copied to the device by a blocking copy: ``torch.tensor``/``as_tensor`` of Python
  data (not visible here: ``Tensor.to(device)`` of a host tensor, which on CPU is a no-op).

Calls made from ``torch/optim`` are not counted: with the default (non-capturable) Adam on CUDA,
the ``step`` counters live on the host and their ``item()`` never waits for the device.

Example:
    >>> with SyncDetector() as det:                       # doctest: +SKIP
    ...     trainer.train_step()
    >>> assert not det.calls, det.report()
"""

from __future__ import annotations

import traceback

import torch
from torch.overrides import TorchFunctionMode

__all__ = ["SyncDetector", "SYNC_FUNCTIONS"]

T = torch.Tensor

#: functions and methods that always synchronise (given a CUDA tensor)
SYNC_FUNCTIONS = {
    T.item, T.tolist, T.numpy, T.cpu, T.__bool__, T.__int__, T.__float__, T.__index__,
    T.__format__, T.__repr__, T.__str__, T.nonzero, torch.nonzero, T.argwhere, torch.argwhere,
    T.masked_select, torch.masked_select, T.unique, torch.unique, T.unique_consecutive,
    torch.unique_consecutive, torch.bincount, T.bincount, torch.histc, T.histc,
    torch.multinomial, T.multinomial, torch.equal, T.equal, torch.allclose, T.allclose,
    torch.nanmedian, T.nanmedian, torch.tensor, torch.as_tensor,
}


def _is_bool_tensor(x) -> bool:
    return isinstance(x, torch.Tensor) and x.dtype == torch.bool


def _is_scalar_tensor(x) -> bool:
    return isinstance(x, torch.Tensor) and x.ndim == 0 and not x.dtype.is_floating_point


def _index_syncs(index) -> bool:
    """Boolean masks go through nonzero; a 0-dim integer tensor index is read on the host."""
    items = index if isinstance(index, tuple) else (index,)
    return any(_is_bool_tensor(i) or _is_scalar_tensor(i) for i in items)


def _why(func, args, kwargs) -> str | None:
    if func in SYNC_FUNCTIONS:
        if func in (torch.tensor, torch.as_tensor) and args and isinstance(args[0], torch.Tensor):
            return None  # tensor -> tensor, no host data involved
        return getattr(func, "__qualname__", getattr(func, "__name__", str(func)))
    if func in (T.__getitem__, T.__setitem__) and len(args) > 1 and _index_syncs(args[1]):
        return f"Tensor.{func.__name__} with a boolean or 0-dim tensor index"
    if func is torch.where and len(args) + len(kwargs) == 1:
        return "torch.where(condition) (one argument = nonzero)"
    if func in (torch.repeat_interleave, T.repeat_interleave) and kwargs.get("output_size") is None:
        reps = args[1] if len(args) > 1 else kwargs.get("repeats")
        if isinstance(reps, torch.Tensor) and reps.numel() > 1 or (
                func is torch.repeat_interleave and len(args) == 1 and not kwargs):
            return "repeat_interleave with tensor repeats and no output_size"
    if func in (torch.normal,) and any(isinstance(a, torch.Tensor) for a in args[1:2]):
        return "torch.normal with a tensor std"
    if func in (torch.quantile, T.quantile, torch.nanquantile, T.nanquantile):
        q = args[1] if len(args) > 1 else kwargs.get("q")
        if isinstance(q, torch.Tensor):
            return "quantile with a tensor q"
    return None


class SyncDetector(TorchFunctionMode):
    """Records the calls that would synchronise a CUDA device (module docstring).

    Attributes:
        calls: list of (what, where) with ``where`` the innermost non-torch source line.
    """

    def __init__(self):
        super().__init__()
        self.calls: list[tuple[str, str]] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        why = _why(func, args, kwargs)
        if why is not None:
            where = self._caller()
            if where is not None:
                self.calls.append((why, where))
        return func(*args, **kwargs)

    @staticmethod
    def _caller() -> str | None:
        """The innermost frame outside torch and this file; None for calls from torch/optim."""
        frames = traceback.extract_stack()
        for fr in reversed(frames):
            f = fr.filename.replace("\\", "/")
            if "/torch/optim/" in f:
                return None
            if "/torch/" in f or f.endswith("sync_detector.py"):
                continue
            return f"{f}:{fr.lineno} {fr.line}"
        return "?"

    def report(self) -> str:
        """One line per recorded call."""
        return "\n".join(f"{what} at {where}" for what, where in self.calls)
