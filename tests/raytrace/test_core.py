"""The traversal behind `Tracer` is a pluggable `TraceCore`: the NumPy reference is tested against
the brute-force oracles here, and any other core (a compiled one) against both the oracles and
the reference, ray for ray, as gsplat tests its CUDA path against its PyTorch reference."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.raytrace import TraceCore, Tracer
from scube_sim.raytrace.backends import BACKENDS
from scube_sim.raytrace.reference import PreparedGaussians, ReferenceCore

from .oracles import brute_force_hard, sampled_soft_composite
from .test_tracer import K, random_rays, random_scene

# Every core of this build; a compiled core registers here when it lands.
CORES: dict[str, TraceCore] = {"reference": ReferenceCore()}


class RecordingCore:
    """Delegates to another core and records what it was handed."""

    name = "recording"

    def __init__(self, inner):
        self.inner, self.calls = inner, []

    def trace_hard(self, scene, opts, o, d, tmin, tmax, t_lo, t_hi, stats):
        self.calls.append(("hard", scene, opts, o.shape[0]))
        return self.inner.trace_hard(scene, opts, o, d, tmin, tmax, t_lo, t_hi, stats)

    def trace_soft(self, scene, opts, o, d, tmin, tmax, t_lo, t_hi, stats):
        self.calls.append(("soft", scene, opts, o.shape[0]))
        return self.inner.trace_soft(scene, opts, o, d, tmin, tmax, t_lo, t_hi, stats)


@pytest.mark.parametrize("core", sorted(CORES))
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mode", ["entry", "max_response"])
def test_core_nearest_hit_equals_brute_force(core, backend, mode, rng):
    g, rots = random_scene(rng, n=150)
    o, d = random_rays(rng, 1500)
    want = brute_force_hard(o, d, g.means, rots, g.scales, K, mode)
    h = Tracer(g, backend=backend, mode=mode, opacity_floor=0.0, core=CORES[core]).trace(o, d)
    assert np.array_equal(h.hit, np.isfinite(want))
    np.testing.assert_allclose(h.t[h.hit], want[h.hit], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("core", sorted(CORES))
def test_core_soft_compositing_equals_sampled_integration(core, rng):
    g, rots = random_scene(rng, n=20, spread=2.0, smin=0.2, smax=0.8)
    g.opacities = rng.uniform(0.02, 0.5, len(g))
    o, d = random_rays(rng, 30, radius=6.0)
    # embreex has no all-hits listing, so this runs the walk, not open3d's one-traversal listing.
    tr = Tracer(g, backend="embreex", mode="soft", soft_hit_alpha=0.0, core=CORES[core])
    h = tr.trace(o, d, 0.0, 12.0)
    depth, acc = sampled_soft_composite(o, d, g.means, rots, g.scales, g.opacities, K, t_max=12.0)
    has = acc > 0
    assert np.array_equal(h.alpha > 0, has)
    np.testing.assert_allclose(h.t[has], depth[has], atol=2e-3)


@pytest.mark.parametrize("core", sorted(set(CORES) - {"reference"}) or
                         [pytest.param("none", marks=pytest.mark.skip(reason="this build has no core but the reference"))])
@pytest.mark.parametrize("mode", ["entry", "max_response", "soft"])
def test_other_cores_agree_with_the_reference_ray_for_ray(core, mode, rng):
    g, _ = random_scene(rng, n=300)
    o, d = random_rays(rng, 2000)
    ref = Tracer(g, mode=mode, opacity_floor=0.0).trace(o, d)
    got = Tracer(g, mode=mode, opacity_floor=0.0, core=CORES[core]).trace(o, d)
    assert np.array_equal(got.hit, ref.hit) and np.array_equal(got.gaussian, ref.gaussian)
    np.testing.assert_allclose(got.t[got.hit], ref.t[ref.hit], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("mode", ["entry", "soft"])
def test_tracer_hands_the_core_its_prepared_scene(mode, rng):
    g, _ = random_scene(rng, n=40)
    g.opacities = np.where(np.arange(len(g)) % 4 == 0, 0.001, 0.9)  # a quarter below both floors
    rec = RecordingCore(ReferenceCore())
    tr = Tracer(g, mode=mode, core=rec)
    o, d = random_rays(rng, 50)
    h = tr.trace(o, d)
    kind, scene, opts, n = rec.calls[-1]
    assert (kind, n) == ("soft" if mode == "soft" else "hard", 50)
    assert isinstance(scene, PreparedGaussians) and scene is tr.prepared
    assert len(scene.gaussians) == 30 and opts.mode == mode and scene.k == K
    assert np.array_equal(h.t, Tracer(g, mode=mode).trace(o, d).t)  # the wrapper changes nothing


def test_settings_changed_after_the_build_take_effect(rng):
    """`mode` and `exact_order` are read at each trace (the tracer benchmark sweeps them on one
    build): the result equals a tracer built with those settings, and the brute-force oracle."""
    g, rots = random_scene(rng, n=150)
    o, d = random_rays(rng, 1500)
    tr = Tracer(g, mode="entry", opacity_floor=0.0)
    tr.mode = "max_response"
    got = tr.trace(o, d)
    want = brute_force_hard(o, d, g.means, rots, g.scales, K, "max_response")
    assert np.array_equal(got.hit, np.isfinite(want))
    np.testing.assert_allclose(got.t[got.hit], want[got.hit], rtol=1e-9, atol=1e-9)
    tr.exact_order = False
    fast = tr.trace(o, d)
    ref = Tracer(g, mode="max_response", opacity_floor=0.0, exact_order=False).trace(o, d)
    assert np.array_equal(fast.t, ref.t) and np.array_equal(fast.gaussian, ref.gaussian)
