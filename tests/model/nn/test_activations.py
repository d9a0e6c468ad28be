"""The torch activations against their numpy twins (the container's), and at the extremes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from scube_sim import splat_params as sp
from scube_sim.model.nn import activations as act
from scube_sim.transforms import normalize_quat, quat_to_rotmat
from scube_sim.voxsplat import VoxSplat

EXTREMES = [-1e4, -100.0, -60.0, -1.0, 0.0, 1e-13, 1.0, 60.0, 100.0, 1e4]


def raw_params(rng, v=50, m=4, spread=3.0) -> np.ndarray:
    p = rng.normal(0, spread, (v, m, sp.NUM_RAW)).astype(np.float32)
    p[:3, :, :] = rng.choice(EXTREMES, size=(3, m, sp.NUM_RAW)).astype(np.float32)
    p[3, 0, sp.QUAT] = 0.0  # a zero quaternion: the identity
    return p


def test_parity_with_the_container():
    """model.activations.activate gives what VoxSplat's numpy activations give, float32 against
    float64, on random and extreme raw values."""
    rng = np.random.default_rng(0)
    params = raw_params(rng)
    v = params.shape[0]
    ijk = rng.integers(-50, 50, (v, 3)).astype(np.int32)
    vs = VoxSplat(ijk, params, voxel_size=0.2, origin=np.zeros(3), valid=np.ones(params.shape[:2], bool),
                  offset_range=3.0)
    centers = torch.from_numpy(vs.voxel_centers()).float()
    out = act.activate(torch.from_numpy(params), centers, 0.2, 3.0)
    np.testing.assert_allclose(out["means"].numpy(), vs.means(), atol=1e-5)
    np.testing.assert_allclose(out["opacities"].numpy(), vs.opacities(), atol=1e-6)
    np.testing.assert_allclose(out["scales"].numpy(), vs.scales(), rtol=1e-5)
    np.testing.assert_allclose(out["quats"].numpy(), vs.quats(), atol=1e-6)
    np.testing.assert_allclose(out["colors"].numpy(), vs.colors(), atol=1e-6)
    np.testing.assert_allclose(act.rotations(out["quats"]).numpy(), quat_to_rotmat(params[..., sp.QUAT]), atol=1e-5)
    np.testing.assert_array_equal(out["quats"][3, 0].numpy(), [1, 0, 0, 0])


def test_the_paper_formulas():
    """Independent of both implementations: sigmoid, exp, tanh, the SH constant at chosen values."""
    x = torch.tensor([0.0, float(np.log(3.0))])
    torch.testing.assert_close(act.opacities(x), torch.tensor([0.5, 0.75]))
    torch.testing.assert_close(act.scales(torch.tensor([float(np.log(0.25))])), torch.tensor([0.25]))
    torch.testing.assert_close(act.offsets(torch.tensor([float(np.arctanh(0.5))]), 0.3), torch.tensor([0.15]))
    torch.testing.assert_close(act.colors(torch.tensor([0.0, 0.5 / sp.SH_C0, -10.0])), torch.tensor([0.5, 1.0, 0.0]))
    q = act.quats(torch.tensor([[0.0, 0.0, 0.0, 2.0]]))  # 180 degrees about z
    torch.testing.assert_close(act.rotations(q)[0], torch.diag(torch.tensor([-1.0, -1.0, 1.0])))
    # the inverses in splat_params undo the numpy activations
    a = np.array([1e-6, 0.3, 0.999])
    np.testing.assert_allclose(sp.opacities(sp.opacities_to_raw(a)), a, rtol=1e-9)
    np.testing.assert_allclose(sp.scales(sp.scales_to_raw(a)), a, rtol=1e-12)
    np.testing.assert_allclose(sp.offsets(sp.offsets_to_raw(a * 0.3, 0.3), 0.3), a * 0.3, rtol=1e-6)


@pytest.mark.parametrize("value", EXTREMES + [-1e20, 1e20])
def test_bounds_at_extreme_raw_values(value):
    """No NaN, no overflow, finite gradients, values inside their ranges, at any finite raw value."""
    raw = torch.full((2, 4, sp.NUM_RAW), float(value), requires_grad=True)
    out = act.activate(raw, torch.zeros(2, 3), voxel_size=0.1)
    loss = sum(t.sum() for t in out.values()) + act.rotations(out["quats"]).sum()
    loss.backward()
    for name, t in out.items():
        assert torch.isfinite(t).all(), name
    assert torch.isfinite(raw.grad).all()
    assert out["opacities"].min() >= 0 and out["opacities"].max() <= 1
    assert out["scales"].min() >= 1e-9 * 0.999 and out["scales"].max() <= 1e4 * 1.001
    assert out["means"].abs().max() <= 0.3 + 1e-6
    torch.testing.assert_close(out["quats"].norm(dim=-1), torch.ones(2, 4))
    assert out["colors"].min() >= 0 and out["colors"].max() <= 1
    # the numpy twin holds too
    p = np.full((2, 4, sp.NUM_RAW), value, np.float64)
    with np.errstate(all="raise"):
        for f in (sp.opacities, sp.scales, lambda x: sp.offsets(x, 0.3)):
            assert np.isfinite(f(p)).all()
        assert np.isfinite(sp.colors(p)).all()
    assert np.isfinite(normalize_quat(p[..., sp.QUAT])).all()


def test_zero_quaternion_has_a_zero_gradient():
    raw = torch.zeros(1, 4, requires_grad=True)
    q = act.quats(raw)
    (q * torch.tensor([1.0, 2.0, 3.0, 4.0])).sum().backward()
    assert torch.equal(q.detach(), torch.tensor([[1.0, 0, 0, 0]]))
    assert torch.equal(raw.grad, torch.zeros(1, 4))
