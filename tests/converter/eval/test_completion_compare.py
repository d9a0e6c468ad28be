"""The completion comparison's ray-by-ray figures (experiments/completion_compare.py)."""

from __future__ import annotations

import numpy as np
import pytest

from experiments.completion_compare import PAIRED_COUNTS, clear_only, paired, summarise_paired


def test_paired_tells_rays_made_worse_from_rays_gained_on_hand_made_range_images():
    nan = np.nan
    reference = np.array([[10.0, 10.0, 10.0, 10.0, nan, 20.0, 30.0]])
    alone = np.array([[10.1, nan, 12.0, 10.0, 5.0, 20.2, 30.0]])
    completed = np.array([[10.1, 11.0, 10.0, 12.0, 5.0, 20.6, nan]])
    rays = np.isfinite(reference)
    got = paired(reference, rays, alone, completed)
    # ray 0 the same; ray 2 2 m better; ray 3 2 m worse; ray 5 0.4 m worse, within the 0.5 m;
    # ray 1 returned by the completion alone (1 m off); ray 6 lost; ray 4 no reference return
    assert {k: got[k] for k in PAIRED_COUNTS} == {"rays": 6, "both": 4, "worse": 1, "better": 1, "gained": 1, "lost": 1}
    assert got["gained_median_m"] == pytest.approx(1.0) and got["lost_median_m"] == pytest.approx(0.0)
    none = paired(reference, rays, alone, alone)
    assert none["worse"] == none["better"] == none["gained"] == none["lost"] == 0 and np.isnan(none["gained_median_m"])
    assert np.isnan(none["lost_median_m"])


def test_summarise_paired_sums_counts_and_weights_the_gained_median_by_its_rays():
    row = {"ahead_m": 0.0, "split": "all", "rays": 10, "both": 8, "worse": 1, "better": 2, "lost": 0,
           "lost_median_m": float("nan")}
    samples = [{"paired": {"c": [{**row, "gained": 1, "gained_median_m": 4.0}]}},
               {"paired": {"c": [{**row, "gained": 3, "gained_median_m": 0.0}]}},
               {"paired": {"c": [{**row, "gained": 0, "gained_median_m": float("nan")}]}}]
    (got,) = summarise_paired(samples, ["c"])
    assert (got["rays"], got["both"], got["worse"], got["better"], got["gained"]) == (30, 24, 3, 6, 4)
    assert got["gained_median_m"] == pytest.approx(1.0) and np.isnan(got["lost_median_m"])


def test_clear_only_keeps_the_ray_by_ray_rows_of_the_clear_poses():
    samples = [{"sample": "a", "rows": [{"ahead_m": 0.0}, {"ahead_m": 60.0}], "pose_clear": {"0": True, "60": False},
                "paired": {"c": [{"ahead_m": 0.0}, {"ahead_m": 60.0}]}}]
    (got,) = clear_only(samples)
    assert got["paired"] == {"c": [{"ahead_m": 0.0}]} and got["rows"] == samples[0]["rows"]
