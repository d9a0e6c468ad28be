"""Measure how a real sensor's reported intensity depends on incidence and range.

    .venv/bin/python tools/fit_intensity_response.py [--data ../shared/data]

Prints, per sensor of the shared logs, the exponents a and b of ``I ~ cos(theta)^a r^-b``
(`intensity.response.incidence_exponent`, `intensity.falloff_exponent`), two ways:
- across surfaces: least squares of log I on log cos(theta) and log r over one sweep's meshed
  returns above the ground (biased where material and geometry go together: walls face the
  sensor, car sides do not);
- within surfaces (where two sweeps see the same place: Argoverse 2's two stacked VLP-32C, KITTI
  frames 0 and 2): differences of log I, log cos and log r between the sweeps in the same 0.2 m
  voxel, so the material cancels; a per-sweep offset absorbs a gain difference between units.
Incidence comes from the range-image mesh (area-weighted normals around each return).
Noise in the normals biases a towards 0 (errors in the regressor): read a as a lower bound. Zero readings are left out
(log), and so is everything under 1.5 m (ego body) and at grazing incidence (cos < 0.05).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from scube_sim.datasets import open_dataset  # noqa: E402
from scube_sim.realdata.build import height_above_ground, range_image_mesh  # noqa: E402
from scube_sim.voxsplat import unique_voxels  # noqa: E402

LOGS = [("nuscenes", "nuscenes-mmdet3d-demo", "HDL-32E", [0]),
        ("kitti_raw", "kitti-raw-2011_09_26-udacity", "HDL-64E", [0, 2]),
        ("argoverse2", "argoverse2-sensor-log-7fab2350", "VLP-32C", [0])]


def vertex_normals(p: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted normals (N, 3) of the triangles around each point, and which points have any.
    Smoother than one triangle's: noise in the regressor would bias the slope towards 0."""
    n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    n[np.einsum("ij,ij->i", n, p[f[:, 0]]) > 0] *= -1.0  # all facing the sensor (at the origin)
    out = np.zeros_like(p)
    for k in range(3):
        np.add.at(out, f[:, k], n)
    length = np.linalg.norm(out, axis=1)
    has = length > 0
    out[has] /= length[has, None]
    return out, has


def returns(sw):
    """World points (N, 3), log I, log cos, log r of one sweep's usable returns."""
    r = np.linalg.norm(sw.points, axis=1)
    sw = sw.subset(r > 1.5)
    p = sw.points
    n, has = vertex_normals(p, range_image_mesh(p))
    r = np.linalg.norm(p, axis=1)
    cos = np.abs(np.einsum("ij,ij->i", n, p)) / r
    inten = sw.intensity / sw.intensity_max
    ok = has & (cos >= 0.05) & (inten > 0)
    world = sw.world_points()
    return world[ok], np.log(inten[ok]), np.log(cos[ok]), np.log(r[ok])


def across(world, li, lc, lr):
    above = height_above_ground(world) > 0.5
    a = np.stack([np.ones(above.sum()), lc[above], lr[above]], 1)
    coef = np.linalg.lstsq(a, li[above], rcond=None)[0]
    return coef[1], -coef[2], int(above.sum())


def within(sweeps, voxel=0.2):
    """Pairs of sweeps in the same voxel: d log I = a d log cos - b d log r + offset."""
    rows = []
    for k, (world, li, lc, lr) in enumerate(sweeps):
        rows.append(np.c_[np.floor(world / voxel), np.full(len(li), k), li, lc, lr])
    allr = np.concatenate(rows)
    uniq, inv, _ = unique_voxels(allr[:, :3])
    key = inv * len(sweeps) + allr[:, 3].astype(np.int64)
    nk = uniq.shape[0] * len(sweeps)
    cnt = np.bincount(key, minlength=nk)
    means = [np.bincount(key, weights=allr[:, c], minlength=nk) / np.maximum(cnt, 1) for c in (4, 5, 6)]
    cnt = cnt.reshape(-1, len(sweeps))
    m = [x.reshape(-1, len(sweeps)) for x in means]
    both = (cnt[:, 0] >= 1) & (cnt[:, 1] >= 1)
    d = [x[both, 1] - x[both, 0] for x in m]
    a = np.stack([np.ones(both.sum()), d[1], d[2]], 1)
    coef = np.linalg.lstsq(a, d[0], rcond=None)[0]
    return coef[1], -coef[2], int(both.sum()), float(np.std(d[1]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("SCUBE_SIM_SHARED_DATA",
                                                                     REPO.parent / "shared" / "data")))
    args = ap.parse_args(argv)
    for name, folder, model, samples in LOGS:
        ds = open_dataset(name, args.data / folder)
        sweeps = [(i, sw) for i in samples for sw in ds[i].sweeps]
        data = [returns(sw) for _, sw in sweeps]
        for (i, sw), d in zip(sweeps, data):
            a, b, n = across(*d)
            print(f"{model} ({name} sample {i} {sw.sensor}), across surfaces: a = {a:.3f}, b = {b:.3f} ({n} returns)")
        if len(data) == 2:
            a, b, n, spread = within(data)
            what = " vs ".join(f"{i} {sw.sensor}" for i, sw in sweeps)
            print(f"{model} ({name} {what}), within surfaces: a = {a:.3f}, b = {b:.3f} ({n} voxels, "
                  f"std of d log cos {spread:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
