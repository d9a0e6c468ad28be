"""Semi-global aggregation against a direct transcription of Hirschmüller's recursion (loops over
pixels, one path at a time), and its handling of unseen entries and bad arguments."""

import numpy as np
import pytest
import torch

from scube_sim.errors import InputError
from scube_sim.reconstruct.stereo.sgm import semi_global

P1, P2 = 0.05, 0.3
DIRECTIONS_4 = [(0, 1), (0, -1), (1, 0), (-1, 0)]
DIRECTIONS_8 = DIRECTIONS_4 + [(1, 1), (-1, -1), (1, -1), (-1, 1)]


def _reference(cost: np.ndarray, directions, p1=P1, p2=P2) -> np.ndarray:
    """L_r(p, d) = C(p, d) + min(L(p - r, d), L(p - r, d +- 1) + p1, min_k L(p - r, k) + p2) - min_k L(p - r, k),
    L = C where p - r is outside the image; the mean over the directions."""
    d_count, h, w = cost.shape
    total = np.zeros_like(cost, dtype=np.float64)
    for dy, dx in directions:
        lr = np.zeros_like(cost, dtype=np.float64)
        ys = range(h) if dy >= 0 else range(h - 1, -1, -1)
        xs = list(range(w) if dx >= 0 else range(w - 1, -1, -1))
        for y in ys:
            for x in xs:
                py, px = y - dy, x - dx
                if not (0 <= py < h and 0 <= px < w):
                    lr[:, y, x] = cost[:, y, x]
                    continue
                prev = lr[:, py, px]
                m = prev.min()
                for d in range(d_count):
                    cands = [prev[d], m + p2]
                    if d > 0:
                        cands.append(prev[d - 1] + p1)
                    if d < d_count - 1:
                        cands.append(prev[d + 1] + p1)
                    lr[d, y, x] = cost[d, y, x] + min(cands) - m
        total += lr
    return total / len(directions)


@pytest.mark.parametrize("paths", [4, 8])
def test_matches_the_recursion_written_out(paths):
    rng = np.random.default_rng(3)
    cost = rng.uniform(0, 1, (6, 5, 7)).astype(np.float32)
    got = semi_global(torch.from_numpy(cost), P1, P2, paths=paths).numpy()
    want = _reference(cost, DIRECTIONS_4 if paths == 4 else DIRECTIONS_8)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)


def test_a_smooth_surface_in_noise_is_recovered_and_unseen_entries_stay_nan():
    # a plane's true hypothesis (slowly varying) marked by a small dip under uniform noise larger
    # than the dip: per pixel the minimum is mostly wrong, along paths it is right
    rng = np.random.default_rng(5)
    d_count, h, w = 48, 40, 60
    true = (10 + 0.3 * np.arange(w)[None] + 0.1 * np.arange(h)[:, None]).astype(np.int64)
    cost = rng.uniform(0.25, 0.65, (d_count, h, w)).astype(np.float32)
    np.put_along_axis(cost, true[None], 0.3, axis=0)
    cost[:, :3] = np.nan  # rows no source sees
    cost[40:, 10, 10] = np.nan  # hypotheses no source sees at one pixel
    out = semi_global(torch.from_numpy(cost), 0.02, 0.2).numpy()
    assert np.isnan(out[:, :3]).all() and np.isnan(out[40:, 10, 10]).all()
    assert np.isfinite(out[:40, 10, 10]).all() and np.isfinite(out[:, 3:]).sum() == np.isfinite(cost[:, 3:]).sum()
    raw = np.nan_to_num(cost[:, 3:], nan=9).argmin(0) == true[3:]
    agg = np.nan_to_num(out[:, 3:], nan=9).argmin(0) == true[3:]
    assert raw.mean() < 0.05 and agg.mean() > 0.8, (raw.mean(), agg.mean())


def test_bad_arguments_are_refused():
    c = torch.zeros(3, 2, 2)
    with pytest.raises(InputError, match="paths"):
        semi_global(c, 0.1, 0.2, paths=6)
    with pytest.raises(InputError, match="p1"):
        semi_global(c, 0.3, 0.2)
    with pytest.raises(InputError, match=r"\(D, H, W\)"):
        semi_global(torch.zeros(3, 2), 0.1, 0.2)
