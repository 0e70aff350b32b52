"""`mode_depth`: soft argmax restricted to the main mode of a depth distribution."""

import torch

from svolsdf.mvs.backbone import expected_depth, mode_depth


def test_unimodal_equals_expectation():
    # a peaked distribution whose mass lies inside the window: same as the full expectation
    D = 16
    d = torch.linspace(500, 700, D).view(D, 1, 1).expand(D, 3, 4)
    logits = -((torch.arange(D).float() - 6.3) ** 2).view(D, 1, 1) * 4.0
    p = torch.softmax(logits.expand(D, 3, 4), 0)
    torch.testing.assert_close(mode_depth(p, d, radius=3), expected_depth(p, d), rtol=0,
                               atol=1e-3)


def test_bimodal_stays_on_the_stronger_mode():
    D = 32
    d = torch.linspace(400, 800, D).view(D, 1, 1)
    p = torch.zeros(D, 1, 1)
    p[5], p[6], p[25] = 0.35, 0.25, 0.4  # main mode at 5-6 (0.6), wrong match at 25
    # argmax is bin 25 (0.4): the window holds only it
    assert abs(float(mode_depth(p, d, radius=2)) - float(d[25])) < 1e-4
    p[25] = 0.3
    p[5] = 0.45
    got = float(mode_depth(p, d, radius=2))
    want = float((p[5] * d[5] + p[6] * d[6]) / (p[5] + p[6]))
    assert abs(got - want) < 1e-3
    # the full expectation lands between the modes, on no surface
    between = float(expected_depth(p, d))
    assert float(d[8]) < between < float(d[23])


def test_window_is_clipped_at_the_ends():
    D = 8
    d = torch.arange(D).float().view(D, 1, 1) * 10 + 100
    p = torch.zeros(D, 1, 1)
    p[0], p[1], p[7] = 0.6, 0.2, 0.2
    torch.testing.assert_close(mode_depth(p, d, radius=1)[0, 0], torch.tensor(102.5))
