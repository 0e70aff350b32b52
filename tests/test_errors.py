"""`svolsdf.errors`: a Ctrl-C is recorded before it raises, so an error that a library made of it
is never taken for a failure to recover from (a fallback mesh, a file read again)."""

from __future__ import annotations

import os
import signal
import time

import pytest
import torch

from svolsdf.errors import interrupted, raise_if_interrupted, watch_interrupts
from svolsdf.fusion.mesh_methods import MeshInputs, MeshMethod, run_mesh_method


def ctrl_c_as_pycolmap_reports_it():
    """Send this process a SIGINT while "importing": pycolmap's __init__ turns the interrupted
    import of its C++ backend into this RuntimeError."""
    try:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(1)
    except KeyboardInterrupt:
        raise RuntimeError("Cannot import the C++ backend pycolmap._core.") from None
    raise AssertionError("no SIGINT arrived")


def test_a_sigint_is_recorded_within_and_forgotten_after():
    assert not interrupted()
    with watch_interrupts():
        assert signal.getsignal(signal.SIGINT) is not signal.default_int_handler
        raise_if_interrupted()  # nothing yet
        with pytest.raises(RuntimeError):
            ctrl_c_as_pycolmap_reports_it()
        assert interrupted()
        with watch_interrupts():  # a nested entry keeps it
            assert interrupted()
        with pytest.raises(KeyboardInterrupt):
            raise_if_interrupted()
    assert not interrupted()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_an_ignored_sigint_stays_ignored():
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with watch_interrupts():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_ctrl_c_in_a_mesh_method_is_no_reason_for_the_fallback_mesh():
    # Ctrl-C during Poisson meshing once gave "field (poisson failed: Cannot import ...)", a
    # finished stage with the wrong mesh
    fallback = []

    def field_mesh():
        fallback.append(1)
        return torch.zeros(3, 3), torch.tensor([[0, 1, 2]]), None

    def interrupted_method(m):
        ctrl_c_as_pycolmap_reports_it()

    inputs = MeshInputs(points=None, colours=None, scene=None, observed=None, model=None,
                        field_mesh=field_mesh, mesh=None, depth_step=torch.ones(1),
                        use_masks=False)
    method = MeshMethod("poisson", interrupted_method)
    with watch_interrupts(), pytest.raises(KeyboardInterrupt):
        run_mesh_method(method, inputs)
    assert not fallback
    # a real failure still falls back to the field's zero level
    failing = MeshMethod("poisson", lambda m: (_ for _ in ()).throw(RuntimeError("no faces")))
    with watch_interrupts():
        *_, source = run_mesh_method(failing, inputs)
    assert fallback and source == "field (poisson failed: no faces)"
