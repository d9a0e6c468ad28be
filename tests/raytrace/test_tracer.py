"""Tracer against closed forms and brute force, on every engine (engines.py) and, for meshes,
both Embree backends."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace import HardMode, ReferenceCore, SoftMode, Tracer
from scube_sim.raytrace.backends import BACKENDS
from scube_sim.voxsplat import Gaussians, VoxSplat

from .engines import ENGINES, core_of, mesh_engine
from .oracles import brute_force_hard, ellipsoid_quadratic, quat_from_axis_angle, rodrigues, sampled_soft_composite

K = 3.0


def one_gaussian(mu, axis, angle, scales, opacity=1.0):
    return Gaussians(means=np.asarray(mu, float)[None], scales=np.asarray(scales, float)[None],
                     quats=quat_from_axis_angle(axis, angle)[None], opacities=np.array([opacity]),
                     sh_dc=np.zeros((1, 3), np.float32))


unit3 = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1)
log_scale = st.floats(-4, 2)  # 1e-4 .. 1e2 m


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("mode", ["entry", "max_response"])
@given(axis=unit3, angle=st.floats(0, np.pi), logs=st.tuples(log_scale, log_scale, log_scale),
       mu=st.tuples(*[st.floats(-5, 5)] * 3), seed=st.integers(0, 2**31))
@settings(max_examples=40)
def test_single_gaussian_matches_closed_form(engine, mode, axis, angle, logs, mu, seed):
    scales = 10.0 ** np.array(logs)
    rng = np.random.default_rng(seed)
    rot = rodrigues(axis, angle)
    g = one_gaussian(mu, axis, angle, scales)
    n = 64
    # Origins outside the ellipsoid, 1.5 to 50 of its largest radii away; aims spread over a
    # region 1.3 times the ellipsoid so about half the rays hit.
    dirs_out = rng.normal(size=(n, 3))
    dirs_out /= np.linalg.norm(dirs_out, axis=1, keepdims=True)
    dist = K * scales.max() * rng.uniform(1.5, 50, n)
    o = np.asarray(mu) + dirs_out * dist[:, None]
    u = rng.normal(size=(n, 3))
    u *= (rng.uniform(0, 1.3, n) ** (1 / 3) / np.linalg.norm(u, axis=1))[:, None]
    target = np.asarray(mu) + (u * K * scales) @ rot.T
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)

    disc, t_near, _, t_peak = ellipsoid_quadratic(o, d, mu, rot, scales, K)
    h = Tracer(g, HardMode(mode, k=K, opacity_floor=0.0), core=core_of(engine)).trace(o, d)

    # Rays within 1e-6 (relative) of tangency are ambiguous in any finite precision: skip them.
    clear = np.abs(disc) > 1e-6 * K * K
    expect_hit = disc > 0
    assert np.array_equal(h.hit[clear], expect_hit[clear])
    want = t_near if mode == "entry" else t_peak
    both = h.hit & expect_hit
    np.testing.assert_allclose(h.t[both], want[both], rtol=1e-4, atol=0)
    assert np.all(np.isfinite(h.points[h.hit]))


def random_scene(rng, n=60, spread=4.0, smin=0.02, smax=0.6):
    axes = rng.normal(size=(n, 3))
    angles = rng.uniform(0, np.pi, n)
    scales = np.exp(rng.uniform(np.log(smin), np.log(smax), (n, 3)))
    means = rng.uniform(-spread, spread, (n, 3))
    quats = np.array([quat_from_axis_angle(a, t) for a, t in zip(axes, angles)])
    rots = np.array([rodrigues(a, t) for a, t in zip(axes, angles)])
    g = Gaussians(means=means, scales=scales, quats=quats, opacities=rng.uniform(0.2, 1.0, n),
                  sh_dc=np.zeros((n, 3), np.float32))
    return g, rots


def random_rays(rng, n, radius=9.0):
    o = rng.normal(size=(n, 3))
    o *= radius / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-3, 3, (n, 3)) - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("mode", ["entry", "max_response"])
@pytest.mark.parametrize("proxy", ["octahedron", "icosahedron"])
def test_overlapping_gaussians_nearest_hit_equals_brute_force(engine, mode, proxy, rng):
    g, rots = random_scene(rng)
    o, d = random_rays(rng, 3000)
    want = brute_force_hard(o, d, g.means, rots, g.scales, K, mode)
    h = Tracer(g, HardMode(mode, opacity_floor=0.0), core=core_of(engine, proxy)).trace(o, d)
    assert np.array_equal(h.hit, np.isfinite(want))
    np.testing.assert_allclose(h.t[h.hit], want[h.hit], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("engine", ENGINES)
def test_voxel_box_proxies_give_the_same_hits(engine, rng):
    g, rots = random_scene(rng, n=200, spread=2.0, smin=0.01, smax=0.15)
    vs = VoxSplat.from_gaussians(g, voxel_size=0.4)
    gg = vs.gaussians()
    rots2 = gg.rotations()
    o, d = random_rays(rng, 3000, radius=6.0)
    want = brute_force_hard(o, d, gg.means, rots2, gg.scales, K, "entry")
    for proxy in ("voxel_box", "octahedron"):
        h = Tracer(vs, HardMode(opacity_floor=0.0), core=core_of(engine, proxy)).trace(o, d)
        assert np.array_equal(h.hit, np.isfinite(want)), proxy
        np.testing.assert_allclose(h.t[h.hit], want[h.hit], rtol=1e-6, atol=1e-6)
        # labels and voxels follow the Gaussian that was hit
        assert np.all(h.voxel[h.hit] == gg.voxel[h.gaussian[h.hit]])


@pytest.mark.parametrize("engine", ENGINES)
def test_soft_mode_matches_sampled_compositing(engine, rng):
    # Faint, large, overlapping Gaussians as in splat files trained without a scaffold.
    g, rots = random_scene(rng, n=25, spread=2.0, smin=0.2, smax=0.8)
    g.opacities = rng.uniform(0.02, 0.5, len(g))
    o, d = random_rays(rng, 40, radius=6.0)
    tr = Tracer(g, SoftMode(hit_alpha=0.0, min_transmittance=1e-3), core=core_of(engine))
    h = tr.trace(o, d, 0.0, 12.0)
    depth, acc = sampled_soft_composite(o, d, g.means, rots, g.scales, g.opacities, K, t_max=12.0)
    has = acc > 0
    assert np.array_equal(h.alpha > 0, has)
    # The sampled peak is within half a grid step (6e-5 m) of the true one.
    np.testing.assert_allclose(h.t[has], depth[has], atol=2e-3)
    np.testing.assert_allclose(h.alpha[has], acc[has], atol=2e-4)


@pytest.mark.parametrize("engine", ENGINES)
def test_soft_single_gaussian_through_centre(engine):
    g = one_gaussian([5, 0, 0], [0, 0, 1], 0.3, [0.5, 0.2, 0.3], opacity=0.4)
    h = Tracer(g, SoftMode(hit_alpha=0.3), core=core_of(engine)).trace(np.zeros((1, 3)), np.array([[1.0, 0, 0]]))
    assert h.hit[0]
    assert h.t[0] == pytest.approx(5.0, abs=1e-9)
    assert h.alpha[0] == pytest.approx(0.4, abs=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_mesh_first_hit_is_exact(backend, rng):
    # A tilted square: the plane through p0 with normal n.
    n = np.array([1.0, 0.3, -0.2])
    n /= np.linalg.norm(n)
    u = np.cross(n, [0, 0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    p0 = np.array([20.0, 1.0, 2.0])
    corners = np.array([p0 + 30 * (a * u + b * v) for a, b in [(-1, -1), (1, -1), (1, 1), (-1, 1)]])
    mesh = TriangleMesh(corners, np.array([[0, 1, 2], [0, 2, 3]]), labels=np.array([14, 14]))
    o = rng.uniform(-2, 2, (500, 3))
    d = (p0 + rng.uniform(-10, 10, (500, 1)) * u + rng.uniform(-10, 10, (500, 1)) * v) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    h = Tracer(mesh, core=mesh_engine(backend)).trace(o, d)
    t_true = ((p0 - o) @ n) / (d @ n)
    assert h.hit.all()
    np.testing.assert_allclose(h.t, t_true, rtol=1e-12)
    assert np.all(h.label == 14)
    assert np.all(np.einsum("ij,ij->i", h.normals, d) < 0)


# --- degenerate inputs ----------------------------------------------------------------------


@pytest.mark.parametrize("engine", ENGINES)
def test_zero_quaternion_and_zero_scale_are_defined(engine):
    g = Gaussians(means=np.array([[5.0, 0, 0], [0, 5.0, 0]]), scales=np.array([[0.3, 0.3, 0.0], [0.2, -0.2, 0.2]]),
                  quats=np.array([[0.0, 0, 0, 0], [0.0, 0, 0, 0]]), opacities=np.array([1.0, 1.0]),
                  sh_dc=np.zeros((2, 3), np.float32))
    tr = Tracer(g, core=core_of(engine))
    h = tr.trace(np.zeros((2, 3)), np.array([[1.0, 0, 0], [0, 1.0, 0]]))
    # zero quaternion = identity; zero scale = a flat disc facing x... here the disc lies in the
    # xy-plane (third axis flat), so a ray along x travels in its plane and enters at 5 - 0.9.
    assert h.hit.all()
    np.testing.assert_allclose(h.t, [5 - 0.9, 5 - 0.6], atol=1e-6)


@pytest.mark.parametrize("engine", ENGINES)
def test_ray_parallel_to_disc(engine):
    g = one_gaussian([0, 0, 0], [0, 0, 1], 0.0, [1.0, 1.0, 1e-9])
    tr = Tracer(g, HardMode(opacity_floor=0.0), core=core_of(engine))
    o = np.array([[-10.0, 0, 0], [-10.0, 0, 1e-6], [-10.0, 0, 0]])
    d = np.array([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0.2, 0]])
    h = tr.trace(o, d)
    assert h.hit.tolist() == [True, False, True]
    np.testing.assert_allclose(h.t[0], 7.0, rtol=1e-12)
    assert np.all(np.isfinite(h.points[h.hit])) and np.all(np.isfinite(h.normals))


def test_bad_inputs_raise_clear_errors():
    g = one_gaussian([0, 0, 0], [0, 0, 1], 0.0, [1.0, 1.0, 1.0])
    g.means[0, 1] = np.nan
    with pytest.raises(ValueError, match="means contains NaN"):
        Tracer(g)
    g = one_gaussian([0, 0, 0], [0, 0, 1], 0.0, [1.0, 1.0, 1.0])
    tr = Tracer(g)
    with pytest.raises(ValueError, match="NaN or Inf"):
        tr.trace(np.array([[np.inf, 0, 0]]), np.array([[1.0, 0, 0]]))
    with pytest.raises(ValueError, match="zero length"):
        tr.trace(np.zeros((1, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="mode"):
        Tracer(g, mode="fuzzy")


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_scene_misses_everything(backend):
    empty = Gaussians(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0), np.zeros((0, 3), np.float32))
    for engine in ENGINES:
        core = core_of(engine) if engine == "compiled" else ReferenceCore(backend)
        for mode in ("entry", "soft"):
            h = Tracer(empty, mode, core=core).trace(np.zeros((4, 3)), np.eye(4, 3) + [0, 0, 1])
            assert not h.hit.any()
    mesh = TriangleMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32))
    assert not Tracer(mesh, core=mesh_engine(backend)).trace(np.zeros((2, 3)), [[1, 0, 0], [0, 1, 0]]).hit.any()


@given(data=st.data())
@settings(max_examples=30)
def test_degenerate_gaussians_never_give_nan_points(data):
    n = data.draw(st.integers(1, 6))
    means = np.array(data.draw(st.lists(st.tuples(*[st.floats(-3, 3)] * 3), min_size=n, max_size=n)))
    scales = np.array(data.draw(st.lists(st.tuples(*[st.sampled_from([0.0, -0.1, 1e-9, 1e-4, 0.5, 100.0])] * 3),
                                         min_size=n, max_size=n)))
    quats = np.array(data.draw(st.lists(st.tuples(*[st.sampled_from([0.0, 1.0, -0.5, 1e-30])] * 4),
                                        min_size=n, max_size=n)))
    g = Gaussians(means, scales, quats, np.ones(n), np.zeros((n, 3), np.float32))
    rng = np.random.default_rng(data.draw(st.integers(0, 1000)))
    o, d = random_rays(rng, 200, radius=8.0)
    for mode in ("entry", "max_response", "soft"):
        for engine in ("compiled", "reference-embreex"):
            h = Tracer(g, mode, core=core_of(engine)).trace(o, d)
            assert np.all(np.isfinite(h.t[h.hit])) and np.all(np.isfinite(h.points[h.hit]))
            assert np.all(np.isfinite(h.normals))


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("proxy", ["octahedron", "icosahedron", "voxel_box"])
def test_lattice_of_identical_gaussians(engine, proxy, rng):
    # Gaussians fitted on a plane share orientation and size: their proxies' faces would lie in
    # common planes, where Embree reports one face of several. The nearest hit must not change.
    xs, ys = np.meshgrid(np.arange(-1.0, 1.01, 0.1), np.arange(-1.0, 1.01, 0.1))
    n = xs.size
    means = np.c_[xs.ravel(), ys.ravel(), np.zeros(n)]
    scales = np.tile([0.03, 0.03, 0.002], (n, 1))
    g = Gaussians(means, scales, np.tile([1.0, 0, 0, 0], (n, 1)), np.ones(n), np.zeros((n, 3), np.float32))
    scene = VoxSplat.from_gaussians(g, 0.2) if proxy == "voxel_box" else g
    gg = scene.gaussians() if proxy == "voxel_box" else g
    o = np.c_[rng.uniform(-3, 3, (4000, 2)), rng.uniform(0.5, 4, 4000)]
    d = np.c_[rng.uniform(-0.9, 0.9, (4000, 2)), np.zeros(4000)] - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rots = gg.rotations()
    want = brute_force_hard(o, d, gg.means, rots, gg.scales, K, "entry")
    tracer = Tracer(scene, HardMode(opacity_floor=0.0), core=core_of(engine, proxy))
    h = tracer.trace(o - (scene.origin if proxy == "voxel_box" else 0), d)
    assert np.array_equal(h.hit, np.isfinite(want))
    np.testing.assert_allclose(h.t[h.hit], want[h.hit], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("engine", ENGINES)
def test_gaussians_below_the_floor_are_dropped_and_the_rest_keep_their_reflectance_and_label(engine):
    # Five round Gaussians in five voxels along y, each with its own reflectance and label; the
    # second and fourth are fainter than the floor. A ray down x through each: the faint ones
    # are missed, the others hit on their sphere (entry at 3 sigma) with their own values.
    ys = np.arange(5) * 2.0
    opac = np.array([0.9, 0.01, 0.6, 0.04, 0.99])
    g = Gaussians(means=np.c_[np.zeros(5), ys, np.zeros(5)], scales=np.full((5, 3), 0.1),
                  quats=np.tile([1.0, 0.0, 0.0, 0.0], (5, 1)), opacities=opac, sh_dc=np.zeros((5, 3), np.float32))
    vs = VoxSplat.from_gaussians(g, voxel_size=0.4, labels=np.arange(5) + 3)
    order = vs.gaussians()  # which (voxel, slot) holds which of the five
    which = np.array([int(np.argmin(np.abs(ys - y))) for y in order.means[:, 1] + order.origin[1]])
    refl = np.zeros(vs.valid.shape, np.float32)
    refl[order.voxel, order.slot] = 0.1 * (which + 1)
    vs.set_channel("reflectance", refl)
    tracer = Tracer(vs, HardMode(opacity_floor=0.05), core=core_of(engine))
    assert len(tracer.gaussians) == 3
    h = tracer.trace_world(np.c_[np.full(5, -5.0), ys, np.zeros(5)], np.tile([1.0, 0.0, 0.0], (5, 1)))
    np.testing.assert_array_equal(h.hit, opac >= 0.05)
    np.testing.assert_allclose(h.t[h.hit], 5.0 - 0.3, atol=1e-6)
    np.testing.assert_allclose(h.reflectance[h.hit], 0.1 * (np.nonzero(opac >= 0.05)[0] + 1), rtol=1e-6)
    assert np.all(np.isnan(h.reflectance[~h.hit]))
    np.testing.assert_array_equal(h.label[h.hit], vs.labels[h.voxel[h.hit]])
