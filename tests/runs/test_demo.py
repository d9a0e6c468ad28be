"""The demo's converted-vs-mesh comparison, by hand on small range images."""

import numpy as np

from scube_sim.lidar.compare import sweep_agreement


def test_sweep_agreement_by_hand():
    nan = np.nan
    ref = np.array([[10.0, 20.0, nan, 5.0], [8.0, 8.0, 8.0, nan]])
    cand = np.array([[10.5, nan, 7.0, 6.0], [8.0, 9.0, nan, 3.0]])
    rays = np.isfinite(ref)  # 6 rays with a reference return
    r = sweep_agreement(ref, cand, rays)
    # both return on 4 of them: errors 0.5, 1.0, 0.0, 1.0
    assert r["rays"] == 6 and r["hit_agreement"] == 4 / 6
    assert r["median_m"] == 0.75 and abs(r["p90_m"] - 1.0) < 1e-12
    # a candidate return where the reference has none is not a compared ray
    only = np.zeros_like(rays)
    only[0, 2] = True
    assert sweep_agreement(ref, cand, only)["hit_agreement"] == 0.0
    none = sweep_agreement(ref, cand, np.zeros_like(rays))
    assert none["rays"] == 0 and np.isnan(none["median_m"]) and np.isnan(none["hit_agreement"])
