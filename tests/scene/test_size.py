"""The one working-size rule of every command (`svolsdf.scene.size.working_size`)."""

from __future__ import annotations

from svolsdf.scene.size import working_size


def test_working_size_is_at_most_768_wide_with_sides_multiples_of_8():
    assert working_size(1600, 1200) == (768, 576)
    assert working_size(640, 480) == (640, 480)
    assert working_size(1600, 1200, (96, 72)) == (96, 72)
    # one rule for every command: 700x500 works at 696x496 in mvs and reconstruct alike
    assert working_size(700, 500) == (696, 496)
