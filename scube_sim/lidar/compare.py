"""Two sweeps of the same rays compared: the sensor model used to replay rays for a comparison
(`fidelity_config`: no noise, one return) and the range agreement of two range images
(`sweep_agreement`). The converter's evaluation and the demo use it; `realdata.fidelity` scores
simulated against real sweeps with it.
"""

from __future__ import annotations

import numpy as np

from .config import LidarConfig


def fidelity_config(config: LidarConfig, *, noise: bool = False, drop=None) -> LidarConfig:
    """The sensor model used to replay real rays: the preset's range limits, drops and intensity
    (at output_scale 1: the common 0-1 scale); one return per ray (strongest), no ego-body box
    (the real rays already stop short of it) and, unless asked, no range noise. drop: the drop
    section to replay with (default: the preset's without its grazing cut, which real sensors
    do not have)."""
    upd = {"ego_body": None, "beam": config.beam.model_copy(update={"return_mode": "strongest"}),
           "drop": config.drop.model_copy(update={"max_incidence_deg": 90.0}) if drop is None else drop,
           "intensity": config.intensity.model_copy(update={"output_scale": 1.0})}
    if not noise:
        upd["noise"] = config.noise.model_copy(update={"range_sigma_m": 0.0, "range_sigma_rel": 0.0,
                                                        "quantization_m": 0.0})
    return config.model_copy(update=upd)


def sweep_agreement(reference: np.ndarray, candidate: np.ndarray, rays: np.ndarray) -> dict:
    """A candidate sweep against a reference sweep of the same rays: range images (rings,
    columns) (NaN: no return) and `rays` (rings, columns) bool, the reference's returns compared
    (e.g. those inside the region both scenes cover). Returns median and p90 |range error| in
    metres over the rays where both return, `hit_agreement` the share of `rays` the candidate
    returns too, and `rays` the count."""
    both = rays & np.isfinite(candidate) & np.isfinite(reference)
    err = np.abs(reference - candidate)[both]
    n = int(rays.sum())
    return {"rays": n, "median_m": float(np.median(err)) if err.size else float("nan"),
            "p90_m": float(np.percentile(err, 90)) if err.size else float("nan"),
            "hit_agreement": float(both.sum() / n) if n else float("nan")}


