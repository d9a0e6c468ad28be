"""First-hit voxel casting against an exhaustive slab test of every ray against every voxel."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from scube_sim.model.nn.voxel_rays import VoxelRayCaster, deposit_mean
from scube_sim.raytrace import compiled

from ...raytrace.engines import require_compiled

# Every traversal test runs on both cores; the compiled one is required (tests/raytrace/engines.py).
CORES = ("reference", "compiled")


def need(core: str) -> str:
    if core == "compiled":
        require_compiled()  # skips only where SCUBE_SIM_ALLOW_NO_CORE=1 and the core is not built
    return core


def scene(rng) -> np.ndarray:
    """A ground plane with holes, a wall, a few blobs and one far, lone voxel (empty space to skip)."""
    x, y = np.meshgrid(np.arange(64), np.arange(48), indexing="ij")
    ground = np.stack([x.ravel(), y.ravel(), np.full(x.size, 2)], 1)[rng.random(x.size) > 0.05]
    xs, zs = np.meshgrid(np.arange(10, 40), np.arange(3, 20), indexing="ij")
    wall = np.stack([xs.ravel(), np.full(xs.size, 30), zs.ravel()], 1)
    blobs = [np.round(rng.normal(c, 2.0, (120, 3))).astype(np.int64) for c in ([50, 10, 8], [20, 15, 12])]
    lone = np.array([[120, 90, 70]])
    ijk = np.unique(np.concatenate([ground, wall, *blobs, lone]), axis=0)
    return ijk[(ijk >= 0).all(1)]


def oracle(o, d, ijk, vs, origin):
    """(index, t): the voxel with the smallest entry parameter over all voxels the ray meets."""
    lo = origin + ijk * vs
    hi = lo + vs
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        a = (lo[None] - o[:, None]) * inv[:, None]
        b = (hi[None] - o[:, None]) * inv[:, None]
    # an axis the ray does not move along: inside the slab -> (-inf, inf), outside -> empty
    par = d[:, None, :] == 0
    inside = (o[:, None, :] >= lo[None]) & (o[:, None, :] < hi[None])
    a = np.where(par, np.where(inside, -np.inf, np.inf), a)
    b = np.where(par, np.inf, b)
    t0 = np.minimum(a, b).max(2)
    t1 = np.maximum(a, b).min(2)
    meets = (t0 <= t1) & (t1 >= 0)
    entry = np.where(meets, np.maximum(t0, 0), np.inf)
    idx = entry.argmin(1)
    t = entry[np.arange(len(o)), idx]
    second = np.sort(entry, 1)[:, 1]
    gap = np.where(np.isfinite(t), second - np.where(np.isfinite(t), t, 0), np.inf)
    return np.where(np.isfinite(t), idx, -1), t, gap


@pytest.mark.parametrize("core", CORES)
def test_first_hits_equal_the_exhaustive_slab_test(core):
    rng = np.random.default_rng(0)
    ijk = scene(rng)
    vs, origin = 0.2, np.array([-3.1, 2.05, -0.7])
    n = 1500
    centre = origin + vs * np.array([32, 24, 10])
    o = centre + rng.normal(0, 1.5, (n, 3))
    o[:200] = origin + vs * rng.uniform(-20, 140, (200, 3))  # some outside the grid's box
    d = rng.normal(size=(n, 3))
    d[200:260, :2] = 0.0  # straight up or down
    d[260:300, 1:] = 0.0  # along x
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[300:400] *= 3.7  # not unit: t is the rays' own parameter
    caster = VoxelRayCaster(ijk, vs, origin)
    index, t = caster.first_hit(o, d, core=need(core))
    want_i, want_t, gap = oracle(o, d, ijk, vs, origin)
    clear = gap > 1e-9  # two voxels entered at the same instant: either is right
    assert clear.mean() > 0.9
    np.testing.assert_array_equal(index.numpy()[clear], want_i[clear])
    hit = want_i >= 0
    np.testing.assert_allclose(t.numpy()[hit], want_t[hit], rtol=0, atol=1e-9)
    assert np.isinf(t.numpy()[~hit]).all()
    assert 0.3 < hit.mean() < 0.95  # both hits and misses


@pytest.mark.parametrize("core", CORES)
def test_skipping_reaches_a_lone_far_voxel_and_max_t_is_a_limit(core):
    ijk = np.array([[0, 0, 0], [300, 200, 100]])
    caster = VoxelRayCaster(ijk, 0.1)
    target = np.array([300.5, 200.5, 100.5]) * 0.1
    o = np.array([[0.05, 0.05, 0.15], [0.05, 0.05, 0.25]])
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    index, t = caster.first_hit(o, d, core=need(core))
    assert index.tolist() == [1, 1]
    dist = np.linalg.norm(target - o, axis=1)
    assert np.all(t.numpy() < dist) and np.all(t.numpy() > dist - 0.1 * np.sqrt(3) / 2 - 1e-9)
    index, _ = caster.first_hit(o, d, max_t=float(dist.min()) - 0.2, core=core)
    assert index.tolist() == [-1, -1]
    empty = VoxelRayCaster(np.zeros((0, 3)), 0.1)
    assert empty.first_hit(o, d, core=core)[0].tolist() == [-1, -1]


@pytest.mark.parametrize("seed", range(3))
def test_compiled_core_gives_the_torch_loops_voxel_and_t_on_every_ray(seed):
    """The same traversal, operation for operation: equal voxels and entry parameters on random
    rays, rays along the axes, rays starting on voxel corners and faces (where the two slab
    parameters tie) and rays that never reach the grid."""
    rng = np.random.default_rng(seed)
    ijk = scene(rng)
    vs, origin = [0.2, 0.4, 0.1][seed], rng.uniform(-5, 5, 3)
    n = 4000
    o = origin + vs * rng.uniform(-10, 130, (n, 3))
    o[:500] = origin + vs * rng.integers(-4, 70, (500, 3))  # on voxel corners
    o[500:800, 0] = origin[0] + vs * rng.integers(0, 64, 300)  # on voxel faces
    target = origin + vs * (ijk[rng.integers(0, len(ijk), n)] + rng.uniform(0, 1, (n, 3)))
    d = target - o + rng.normal(0, 0.5, (n, 3))  # most of them towards a voxel
    axis = rng.integers(0, 3, 600)
    d[1000:1600] = 0.0
    d[np.arange(1000, 1600), axis] = rng.choice([-1.0, 1.0], 600)  # along the axes
    d[1600:1800, 2] = 0.0  # level
    d[1800:2000] *= 1e-3  # short, not unit: t is the rays' own parameter
    want_i, want_t = VoxelRayCaster(ijk, vs, origin).first_hit(o, d, core="reference")
    caster = VoxelRayCaster(ijk, vs, origin)
    got_i, got_t = caster.first_hit(o, d, core=need("compiled"))
    assert torch.equal(got_i, want_i)
    assert torch.equal(got_t, want_t)
    assert 0.2 < (want_i >= 0).float().mean() < 0.95
    lim_i, _ = caster.first_hit(o, d, max_t=2.0, core="compiled")
    assert torch.equal(lim_i, VoxelRayCaster(ijk, vs, origin).first_hit(o, d, max_t=2.0, core="reference")[0])


def test_the_compiled_core_by_name_where_it_is_not_built(monkeypatch):
    monkeypatch.setattr(compiled, "_core", None)
    caster = VoxelRayCaster(np.zeros((1, 3), np.int64), 0.1)
    with pytest.raises(compiled.CoreUnavailable, match="not built"):
        caster.first_hit(np.zeros((1, 3)), np.ones((1, 3)), core="compiled")
    with pytest.raises(ValueError, match="core"):
        caster.first_hit(np.zeros((1, 3)), np.ones((1, 3)), core="gpu")


def test_deposit_averages_features_per_voxel_and_passes_gradients():
    feats = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0], [7.0, 8.0]], requires_grad=True)
    index = torch.tensor([2, -1, 2, 0])
    mean, count = deposit_mean(feats, index, 3)
    torch.testing.assert_close(mean, torch.tensor([[7.0, 8.0], [0.0, 0.0], [3.0, 4.0]]))
    assert count.tolist() == [1, 0, 2]
    mean.sum().backward()
    torch.testing.assert_close(feats.grad, torch.tensor([[0.5, 0.5], [0, 0], [0.5, 0.5], [1, 1]]))
