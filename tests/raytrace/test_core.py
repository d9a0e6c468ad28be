"""The traversal behind `Tracer` is a pluggable `TraceCore`: every core is tested against the
brute-force oracles here, and the compiled core against the NumPy reference, ray for ray, as
gsplat tests its CUDA path against its PyTorch reference."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from scube_sim.raytrace import HardMode, MeshEngine, SoftMode, Tracer, compiled
from scube_sim.raytrace.contracts import SceneGaussians
from scube_sim.raytrace.reference import PreparedGaussians, ReferenceCore

from .engines import ALLOW_NO_CORE, core_of, mesh_engine, require_compiled
from .oracles import brute_force_hard, sampled_soft_composite
from .test_tracer import K, random_rays, random_scene

# Every core of this build, by the Tracer's name for it.
CORES = ("compiled", "reference")


def core_by_name(core: str, **compiled_settings):
    """The core of CORES named `core` (the reference on its default backend)."""
    return core_of("compiled", **compiled_settings) if core == "compiled" else ReferenceCore()


class RecordingCore:
    """Delegates to another core and records what it was handed."""

    name = "recording"

    def __init__(self, inner):
        self.inner, self.calls = inner, []

    def prepare(self, scene):
        self.calls.append(("prepare", scene))
        return self.inner.prepare(scene)

    def trace(self, prepared, mode, o, d, tmin, tmax, stats):
        self.calls.append(("trace", prepared, mode, o.shape[0]))
        return self.inner.trace(prepared, mode, o, d, tmin, tmax, stats)


def test_the_compiled_core_is_built():
    """`make test` fails where the compiled core does not import (SCUBE_SIM_ALLOW_NO_CORE=1 opts out)."""
    if ALLOW_NO_CORE and not compiled.available():
        pytest.skip(f"SCUBE_SIM_ALLOW_NO_CORE=1: {compiled.load_error()}")
    assert compiled.available(), f"the compiled tracer core does not import: {compiled.load_error()}"
    assert compiled.embree_version().startswith(("3.", "4."))
    g, _ = random_scene(np.random.default_rng(0), n=5)
    assert Tracer(g).core_name == "compiled"  # the default wherever it is built


@pytest.mark.parametrize("core", CORES)
@pytest.mark.parametrize("mode", ["entry", "max_response"])
def test_core_nearest_hit_equals_brute_force(core, mode, rng):
    g, rots = random_scene(rng, n=150)
    o, d = random_rays(rng, 1500)
    want = brute_force_hard(o, d, g.means, rots, g.scales, K, mode)
    h = Tracer(g, HardMode(mode, opacity_floor=0.0), core=core_by_name(core)).trace(o, d)
    assert np.array_equal(h.hit, np.isfinite(want))
    np.testing.assert_allclose(h.t[h.hit], want[h.hit], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("core", CORES)
def test_core_soft_compositing_equals_sampled_integration(core, rng):
    g, rots = random_scene(rng, n=20, spread=2.0, smin=0.2, smax=0.8)
    g.opacities = rng.uniform(0.02, 0.5, len(g))
    o, d = random_rays(rng, 30, radius=6.0)
    # embreex has no all-hits listing, so the reference runs its walk, not open3d's listing.
    engine = core_by_name(core) if core == "compiled" else ReferenceCore("embreex")
    tr = Tracer(g, SoftMode(hit_alpha=0.0), core=engine)
    h = tr.trace(o, d, 0.0, 12.0)
    depth, acc = sampled_soft_composite(o, d, g.means, rots, g.scales, g.opacities, K, t_max=12.0)
    has = acc > 0
    assert np.array_equal(h.alpha > 0, has)
    np.testing.assert_allclose(h.t[has], depth[has], atol=2e-3)


@pytest.mark.parametrize("mode", ["entry", "max_response", "soft"])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_compiled_agrees_with_the_reference_ray_for_ray(mode, seed):
    rng = np.random.default_rng(seed)
    g, _ = random_scene(rng, n=300, smin=0.01, smax=0.8)
    g.opacities = rng.uniform(0.01, 1.0, len(g))
    o, d = random_rays(rng, 4000)
    # Soft rays may start inside Gaussians; a reference hard ray starting inside a proxy can miss
    # it (see reference.py), so hard rays start outside them all (the exhaustive test has both).
    tmin = rng.uniform(0.0, 4.0, len(o)) if mode == "soft" else np.zeros(len(o))
    trace_as = SoftMode() if mode == "soft" else HardMode(mode, opacity_floor=0.0)
    ref = Tracer(g, trace_as, core="reference").trace(o, d, tmin, 30.0)
    got = Tracer(g, trace_as, core=core_of("compiled")).trace(o, d, tmin, 30.0)
    assert got.hit.any() and not got.hit.all()
    assert np.array_equal(got.hit, ref.hit) and np.array_equal(got.gaussian, ref.gaussian)
    # Soft depths are weighted means summed in another order (the reference's global cumsum).
    tol = 1e-10 if mode == "soft" else 1e-12
    np.testing.assert_allclose(got.t[got.hit], ref.t[ref.hit], rtol=tol, atol=tol)
    np.testing.assert_allclose(got.points[got.hit], ref.points[ref.hit], rtol=tol, atol=tol)
    np.testing.assert_allclose(got.normals, ref.normals, atol=1e-6)
    assert np.array_equal(got.voxel, ref.voxel) and np.array_equal(got.label, ref.label)
    assert np.array_equal(got.color, ref.color)
    np.testing.assert_allclose(got.alpha, ref.alpha, atol=1e-6)


@pytest.mark.parametrize("start_inside", [False, True])
def test_compiled_equals_an_exhaustive_listing_on_a_voxsplat(start_inside, rng):
    """Against every (ray, Gaussian) pair tested exactly (no acceleration at all), including rays
    that start inside Gaussians (t_min > 0), where the nearest hit is at t_min."""
    from scube_sim.raytrace import gaussian_math as gm
    from scube_sim.voxsplat import VoxSplat

    g, _ = random_scene(rng, n=400, spread=3.0, smin=0.02, smax=0.3)
    vs = VoxSplat.from_gaussians(g, voxel_size=0.5)
    tr = Tracer(vs, HardMode(opacity_floor=0.0), core=core_of("compiled"))
    o, d = random_rays(rng, 800, radius=7.0)
    o = o - tr.origin
    tmin = rng.uniform(4.0, 10.0, len(o)) if start_inside else np.zeros(len(o))
    h = tr.trace(o, d, tmin, 30.0)
    sg = tr.scene_gaussians
    n, m = o.shape[0], len(sg.gaussians)
    ri, gi = np.repeat(np.arange(n), m), np.tile(np.arange(m), n)
    ts, d2, half = gm.ray_ellipsoid(o[ri], d[ri], sg.mu[gi], sg.a[gi], K)
    ok = (d2 <= K * K) & (ts + half >= tmin[ri]) & (ts - half <= 30.0)
    t_hit = np.where(ok, np.maximum(ts - half, tmin[ri]), np.inf)
    best = np.full(n, np.inf)
    np.minimum.at(best, ri, t_hit)
    assert np.array_equal(h.hit, np.isfinite(best))
    if start_inside:
        assert np.sum(h.t[h.hit] == tmin[h.hit]) > 20  # many rays start inside a Gaussian
    np.testing.assert_allclose(h.t[h.hit], best[h.hit], rtol=1e-12, atol=1e-12)
    assert np.all(h.voxel[h.hit] == sg.voxel[h.gaussian[h.hit]])


@pytest.mark.parametrize("mode", ["entry", "max_response", "soft"])
def test_compiled_gives_the_same_bytes_for_any_thread_count(mode, rng):
    g, _ = random_scene(rng, n=500, smin=0.05, smax=0.9)
    g.opacities = rng.uniform(0.02, 0.9, len(g))
    o, d = random_rays(rng, 20_000)
    outs = [Tracer(g, mode, core=core_of("compiled", threads=t)).trace(o, d) for t in (1, 2, 3, 8)]
    for h in outs[1:]:
        for name in h.__dataclass_fields__:
            assert getattr(h, name).tobytes() == getattr(outs[0], name).tobytes(), name


@pytest.mark.parametrize("mode", ["entry", "max_response", "soft"])
def test_the_storage_order_and_the_input_order_change_no_answer(mode, rng, monkeypatch):
    """The core stores Gaussians in Morton order of their means: the same bytes as storing them as
    given, and shuffling the input only renumbers the Gaussians in the answer."""
    if not compiled.available():
        pytest.skip(f"the compiled core is not built: {compiled.load_error()}")
    g, _ = random_scene(rng, n=600, spread=3.0, smin=0.05, smax=0.8)
    g.opacities = rng.uniform(0.02, 0.9, len(g))
    o, d = random_rays(rng, 5000, radius=7.0)
    def trace(gs, morton):
        with monkeypatch.context() as m:
            m.setattr(compiled, "_build", functools.partial(compiled._build, morton=morton))
            tr = Tracer(gs, SoftMode(hit_alpha=0.1) if mode == "soft" else mode, core=core_of("compiled"))
            return tr.trace(o, d), tr.gaussians.means

    (a, means), (b, _) = trace(g, True), trace(g, False)
    assert a.hit.sum() > 500
    for name in a.__dataclass_fields__:
        assert getattr(a, name).tobytes() == getattr(b, name).tobytes(), name
    perm = rng.permutation(len(g))
    shuffled = type(g)(**{f: (v[perm] if isinstance(v, np.ndarray) and len(v) == len(g) else v)
                          for f, v in vars(g).items()})
    c, c_means = trace(shuffled, True)
    assert np.array_equal(c.hit, a.hit) and c.t.tobytes() == a.t.tobytes()
    # Hits name Gaussians by their index in the tracer's kept Gaussians (opacity floor applied).
    assert np.array_equal(c_means[c.gaussian[c.hit]], means[a.gaussian[a.hit]])


def test_soft_k_buffer_size_changes_the_work_not_the_answer(rng):
    """A small k-buffer re-traverses more often; the composited answer is the same."""
    g, _ = random_scene(rng, n=200, spread=2.0, smin=0.1, smax=0.6)
    g.opacities = rng.uniform(0.02, 0.3, len(g))
    o, d = random_rays(rng, 2000, radius=6.0)
    res = {}
    for kb in (1, 3, 16, 64):
        tr = Tracer(g, SoftMode(hit_alpha=0.0), core=core_of("compiled", k_buffer=kb))
        res[kb] = (tr.trace(o, d), tr.stats.rays_cast)
    ref = res[64][0]
    for kb in (1, 3, 16):
        h = res[kb][0]
        assert np.array_equal(h.hit, ref.hit) and np.array_equal(h.gaussian, ref.gaussian)
        np.testing.assert_allclose(h.t[h.hit], ref.t[ref.hit], rtol=1e-12)
        np.testing.assert_allclose(h.alpha, ref.alpha, rtol=1e-6)
    assert res[1][1] > res[3][1] > res[16][1] >= res[64][1]  # traversals


def test_soft_boxes_end_where_the_response_reaches_alpha_min(rng):
    """A tracer built for soft mode bounds each Gaussian where opacity * exp(-d2 / 2) reaches
    soft_alpha_min (3DGRT's adaptive bounds): the same bytes as k-sigma boxes with fewer exact
    tests; a hard mode or a lower alpha floor asked of it later is answered on k-sigma boxes."""
    g, rots = random_scene(rng, n=400, spread=3.0, smin=0.05, smax=0.7)
    g.opacities = np.exp(rng.uniform(np.log(0.001), 0.0, len(g)))  # many faint Gaussians
    o, d = random_rays(rng, 3000, radius=7.0)
    soft = Tracer(g, SoftMode(hit_alpha=0.0), core=core_of("compiled"))
    ksigma = Tracer(g, HardMode("entry", opacity_floor=1.0 / 255.0), core=core_of("compiled"))
    ksigma.mode = SoftMode(hit_alpha=0.0)
    a, b = soft.trace(o, d), ksigma.trace(o, d)
    assert a.hit.sum() > 100
    for name in a.__dataclass_fields__:
        assert getattr(a, name).tobytes() == getattr(b, name).tobytes(), name
    assert soft.stats.exact_tests < 0.8 * ksigma.stats.exact_tests
    # The soft-built tracer asked for a hard mode: exact against brute force.
    soft.mode = "entry"
    got = soft.trace(o, d)
    want = brute_force_hard(o, d, g.means, rots, g.scales, K, "entry")
    kept = g.opacities >= 1.0 / 255.0
    want_kept = brute_force_hard(o, d, g.means[kept], rots[kept], g.scales[kept], K, "entry")
    assert not np.array_equal(want, want_kept)  # the floor matters here
    assert np.array_equal(got.hit, np.isfinite(want_kept))
    np.testing.assert_allclose(got.t[got.hit], want_kept[got.hit], rtol=1e-9, atol=1e-9)
    # A lower alpha floor than the boxes were built for: the k-sigma boxes answer it.
    soft.mode = ksigma.mode = SoftMode(hit_alpha=0.0, alpha_min=1e-3)
    a, b = soft.trace(o, d), ksigma.trace(o, d)
    assert a.t.tobytes() == b.t.tobytes() and a.alpha.tobytes() == b.alpha.tobytes()


def test_the_core_refuses_a_hard_mode_on_soft_boxes(rng):
    if not compiled.available():
        pytest.skip(f"the compiled core is not built: {compiled.load_error()}")
    g, _ = random_scene(rng, n=20)
    c = [np.ascontiguousarray(x, np.float64) for x in (g.means, g.quats, g.scales, g.opacities)]
    scene = compiled._core.GaussianScene(*c, 3.0, 1e-6, 1.0 / 255.0)
    assert scene.alpha_min == pytest.approx(1.0 / 255.0)
    tr = Tracer(g, mode="soft", core=core_of("compiled"))
    o, d = random_rays(rng, 10)
    with pytest.raises(ValueError, match="soft mode with soft_alpha_min"):
        tr.core.trace(compiled.CompiledScene(tr.scene_gaussians, tr.prepared.lo, tr.prepared.hi, handle=scene),
                      HardMode("entry"), o, d, np.zeros(10), np.full(10, 30.0), tr.stats)


def test_meshes_go_to_the_compiled_core_the_same_bytes_for_any_thread_count(rng):
    """Worlds and actors (triangle meshes) trace on the compiled core by default: the same hits as
    the other Embree engines (refined in float64), the same bytes for any thread count, the far
    limit honoured, a bad face index named."""
    from scube_sim.raytrace.backends import make_backend
    from scube_sim.worlds.street import street_scene

    mesh_engine("compiled")
    mesh = street_scene()
    assert Tracer(mesh).core.backend == "compiled"
    o = np.tile([0.0, -2.0, 1.8], (20_000, 1)) + rng.normal(scale=0.2, size=(20_000, 3))
    d = rng.normal(size=(20_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = [Tracer(mesh, core=MeshEngine(threads=t)).trace(o, d, 0.0, 80.0) for t in (1, 2, 5)]
    for h in got[1:]:
        for name in h.__dataclass_fields__:
            assert getattr(h, name).tobytes() == getattr(got[0], name).tobytes(), name
    ref = Tracer(mesh, core=MeshEngine("open3d")).trace(o, d, 0.0, 80.0)
    assert got[0].hit.sum() > 10_000 and np.mean(got[0].hit == ref.hit) > 0.999
    both = got[0].hit & ref.hit
    assert np.median(np.abs(got[0].t[both] - ref.t[both])) < 1e-9
    backend = make_backend("compiled", mesh.vertices.astype(np.float32), mesh.faces)
    far = np.where(got[0].hit, got[0].t - 0.01, 80.0).astype(np.float32)
    t, prim = backend.first_hit(o.astype(np.float32) - mesh.origin.astype(np.float32), d.astype(np.float32), far)
    assert not np.any(prim[got[0].hit] >= 0)  # every first hit lies beyond its shortened limit
    with pytest.raises(ValueError, match="faces: an index outside the vertices"):
        make_backend("compiled", np.zeros((3, 3), np.float32), np.array([[0, 1, 3]]))


def test_compiled_core_and_embreex_in_one_process(rng):
    """embreex bundles its own Embree 4 and the compiled core links Debian's Embree 3: both load
    and trace side by side in one process."""
    from scube_sim.mesh import TriangleMesh

    g, rots = random_scene(rng, n=50)
    o, d = random_rays(rng, 500)
    mesh = TriangleMesh(np.array([[-20.0, -20, -5], [20, -20, -5], [0, 30, -5]]), np.array([[0, 1, 2]], np.int32))
    m = Tracer(mesh, core=MeshEngine("embreex")).trace(o, d)
    h = Tracer(g, HardMode(opacity_floor=0.0), core=core_of("compiled")).trace(o, d)
    want = brute_force_hard(o, d, g.means, rots, g.scales, K, "entry")
    assert np.array_equal(h.hit, np.isfinite(want)) and m.hit.any()


@pytest.mark.parametrize("mode", ["entry", "soft"])
def test_tracer_hands_the_core_its_prepared_scene(mode, rng):
    g, _ = random_scene(rng, n=40)
    g.opacities = np.where(np.arange(len(g)) % 4 == 0, 0.001, 0.9)  # a quarter below both floors
    rec = RecordingCore(ReferenceCore())
    tr = Tracer(g, mode=mode, core=rec)
    o, d = random_rays(rng, 50)
    h = tr.trace(o, d)
    (kind0, scene), (kind, prepared, traced_as, n) = rec.calls
    assert (kind0, kind, n) == ("prepare", "trace", 50)
    assert isinstance(scene, SceneGaussians) and len(scene.gaussians) == 30 and scene.k == K
    assert isinstance(prepared, PreparedGaussians) and prepared is tr.prepared
    assert isinstance(traced_as, SoftMode if mode == "soft" else HardMode) and traced_as.name == mode
    assert np.array_equal(h.t, Tracer(g, mode=mode, core="reference").trace(o, d).t)  # the wrapper changes nothing


def test_the_core_is_chosen_by_name_or_environment(monkeypatch, rng):
    g, _ = random_scene(rng, n=10)
    assert Tracer(g, core="reference").core_name == "reference"
    monkeypatch.setenv(compiled.CORE_ENV, "reference")
    assert Tracer(g).core_name == "reference"
    monkeypatch.setenv(compiled.CORE_ENV, "fastest")
    with pytest.raises(ValueError, match="SCUBE_SIM_CORE"):
        Tracer(g)
    with pytest.raises(ValueError, match="core"):
        Tracer(g, core="gpu")


def test_a_missing_core_falls_back_once_with_a_warning(monkeypatch, rng):
    monkeypatch.setattr(compiled, "_core", None)
    monkeypatch.setattr(compiled, "_LOAD_ERROR", "ImportError: not built")
    monkeypatch.setattr(compiled, "_WARNED", set())
    monkeypatch.delenv(compiled.CORE_ENV, raising=False)
    g, _ = random_scene(rng, n=10)
    with pytest.warns(compiled.CoreUnavailableWarning, match="not built"):
        assert Tracer(g).core_name == "reference"
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert Tracer(g).core_name == "reference"  # said once
    with pytest.raises(compiled.CoreUnavailable, match="libembree-dev"):
        Tracer(g, core="compiled")


def test_settings_changed_after_the_build_take_effect(rng):
    """`mode` and the reference core's `exact_order` are read at each trace (the tracer benchmark
    sweeps them on one build): the result equals a tracer built with those settings, and the
    brute-force oracle."""
    g, rots = random_scene(rng, n=150)
    o, d = random_rays(rng, 1500)
    for core in CORES:
        tr = Tracer(g, HardMode("entry", opacity_floor=0.0), core=core_by_name(core))
        tr.mode = HardMode("max_response")
        got = tr.trace(o, d)
        want = brute_force_hard(o, d, g.means, rots, g.scales, K, "max_response")
        assert np.array_equal(got.hit, np.isfinite(want))
        np.testing.assert_allclose(got.t[got.hit], want[got.hit], rtol=1e-9, atol=1e-9)
    tr = Tracer(g, HardMode("max_response", opacity_floor=0.0), core="reference")
    tr.core.exact_order = False
    fast = tr.trace(o, d)
    ref = Tracer(g, HardMode("max_response", opacity_floor=0.0), core=ReferenceCore(exact_order=False)).trace(o, d)
    assert np.array_equal(fast.t, ref.t) and np.array_equal(fast.gaussian, ref.gaussian)


def _forked_trace(seed: int) -> bytes:
    rng = np.random.default_rng(seed)
    g, _ = random_scene(rng, n=5000)
    o, d = random_rays(rng, 3000)
    return Tracer(g, HardMode(opacity_floor=0.0), core="compiled").trace(o, d).t.tobytes()


def test_forked_workers_build_and_trace_after_the_parent_did(rng):
    """Embree's build pool (TBB) is not fork-safe in general; `worlds generate --jobs` and the
    training data loaders fork after the parent has traced. The children build and trace, and get
    what the parent gets."""
    import multiprocessing as mp

    require_compiled()
    want = [_forked_trace(s) for s in (1, 2)]
    with mp.get_context("fork").Pool(2) as pool:
        got = pool.map(_forked_trace, [1, 2])
    assert got == want
