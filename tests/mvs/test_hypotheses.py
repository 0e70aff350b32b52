import math

import pytest
import torch

from svolsdf.mvs.hypotheses import (
    STAGE_DEPTHS,
    base_interval,
    guided_hypotheses,
    interval_ratio,
    plane_hypotheses,
    stage_hypotheses,
    stage_width,
)

DTU = (425.0, 425.0 + 191 * 2.65)  # docs/method.md 1.4: [425, 931.15]


def test_stage1_linear_matches_method_formula():
    d = plane_hypotheses(*DTU, 192, 3, 4)
    assert d.shape == (192, 3, 4)
    k = torch.arange(192, dtype=torch.float64)
    expect = DTU[0] + k * (DTU[1] - DTU[0]) / 191  # docs/method.md 2.5
    assert torch.allclose(d[:, 1, 2].double(), expect, atol=1e-3)
    assert torch.allclose(d[1, 0, 0] - d[0, 0, 0], torch.tensor(2.65), atol=1e-3)


def test_stage1_inverse_is_uniform_in_inverse_depth():
    d = plane_hypotheses(1.0, 4.0, 7, 1, 1, inverse=True)[:, 0, 0].double()
    inv = 1 / d
    steps = inv[1:] - inv[:-1]
    assert torch.allclose(steps, steps[0].expand_as(steps), atol=1e-6)
    assert d[0] == pytest.approx(1.0) and d[-1] == pytest.approx(4.0)


def test_guided_hypotheses_formula():
    guide = torch.tensor([[500.0, 600.0]])
    D, iv = 32, 0.5 * base_interval(*DTU)
    h = guided_hypotheses(guide, D, iv)
    assert h.shape == (D, 1, 2)
    lower = 500.0 - D / 2 * iv
    upper = 500.0 + D / 2 * iv
    assert h[0, 0, 0].item() == pytest.approx(lower, rel=1e-6)
    assert h[-1, 0, 0].item() == pytest.approx(upper, rel=1e-6)
    assert (h[1] - h[0])[0, 1].item() == pytest.approx((upper - lower) / (D - 1), rel=1e-4)
    # per-pixel interval
    h2 = guided_hypotheses(guide, 8, torch.tensor([[1.0, 2.0]]))
    assert (h2[-1] - h2[0])[0].tolist() == pytest.approx([8.0, 16.0], rel=1e-5)


def test_widths_dtu_millimetres():
    dbar = base_interval(*DTU)
    assert dbar == pytest.approx(2.6362, abs=1e-4)  # divisor 192, docs/method.md 2.5
    # released: r = 0.5 -> 42.2 mm and 10.5 mm
    assert stage_width(2, *DTU, width="released") == pytest.approx(42.18, abs=0.01)
    assert stage_width(3, *DTU, width="released") == pytest.approx(10.54, abs=0.01)
    # paper: the implementation details' explicit intervals 1, 0.5, 0.5 (as released)
    for stage in (2, 3):
        assert stage_width(stage, *DTU, width="paper") == stage_width(stage, *DTU,
                                                                       width="released")
    # half-default: half of the default CasMVSNet widths 32*2*dbar and 8*1*dbar
    assert stage_width(2, *DTU, width="half-default") == pytest.approx(0.5 * 32 * 2 * dbar)
    assert stage_width(3, *DTU, width="half-default") == pytest.approx(0.5 * 8 * 1 * dbar)
    assert stage_width(1, *DTU) == pytest.approx(506.15)
    assert [interval_ratio(k, "paper") for k in (1, 2, 3)] == [1.0, 0.5, 0.5]
    assert interval_ratio(2, "half-default") == 1.0 and interval_ratio(2, "released") == 0.5


def test_default_width_is_the_papers_explicit_numbers():
    """The config's default mvs.width runs the paper's intervals 1, 0.5, 0.5."""
    from svolsdf.config import Config, preset

    for c in (Config(), preset("paper"), preset("fast")):
        assert [interval_ratio(k, c.mvs.width) for k in (1, 2, 3)] == [1.0, 0.5, 0.5]
    assert STAGE_DEPTHS == (192, 32, 8)


def test_stage_hypotheses_total_width():
    guide = torch.full((2, 3), 700.0)
    for stage in (2, 3):
        for mode in ("paper", "released", "half-default"):
            h = stage_hypotheses(stage, *DTU, 2, 3, guide=guide, width_mode=mode)
            D = STAGE_DEPTHS[stage - 1]
            # the D values span (D - 1) spacings of width/(D - 1): total width D r dbar
            assert (h[-1] - h[0]).mean().item() == pytest.approx(
                stage_width(stage, *DTU, width=mode), rel=1e-5)
            assert h.shape == (D, 2, 3)
            assert (h.mean(0) - 700).abs().max() < 1e-3


def test_bad_inputs():
    with pytest.raises(ValueError):
        plane_hypotheses(5.0, 5.0, 8, 1, 1)
    with pytest.raises(ValueError):
        plane_hypotheses(-1.0, 5.0, 8, 1, 1)
    with pytest.raises(ValueError):
        stage_hypotheses(2, *DTU, 2, 3)
    with pytest.raises(ValueError):
        interval_ratio(2, "wide")
    assert math.isfinite(stage_width(2, *DTU))
