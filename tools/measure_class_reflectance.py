"""Measure the median reflectance of each semantic class on the real logs (the check of the
label -> reflectance defaults in `scube_sim/labels.py`).

    .venv/bin/python tools/measure_class_reflectance.py [--data ../shared/data] [--json out.json]

Each sweep goes through the build's own steps (`reconstruct.accumulate` with the range-image
mesh, `surface_patches` normals, `return_reflectance`: the sensor's response inverted per return),
so the figures are on the scale of the VoxSplat `reflectance` channel. Labels: points inside the
set's labelled boxes take the box's class (nuScenes: 69 boxes; KITTI object: 10); every set also
gives two geometric classes: **ground** (under 0.15 m above the local ground, `height_above_ground`:
road, lane paint, sidewalk and curbs together) and **above ground, unlabelled** (walls,
vegetation, poles, unlabelled objects). No shared log has per-point semantic labels (nuScenes
lidarseg is not in the demo), so background classes are measured only as these mixtures.

Scales: nuScenes' HDL-32E reports calibrated reflectivity (HDL-32E manual: diffuse 0-100 for
0-100 %), so its figures are Lambertian-equivalent reflectance. Argoverse 2's VLP-32C uses the
same convention by assumption (its manual was not at hand). KITTI's HDL-64E reflectance has no
published scale (preset gain 1): printed for comparison, not used.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from scube_sim.datasets import open_dataset  # noqa: E402
from scube_sim.labels import LABEL_NAMES  # noqa: E402
from scube_sim.realdata.build import accumulate, height_above_ground, return_reflectance, surface_patches  # noqa: E402

LOGS = [("nuscenes", "nuscenes-mmdet3d-demo", [0], "calibrated (HDL-32E reflectivity)"),
        ("argoverse2", "argoverse2-sensor-log-7fab2350", [0], "assumed calibrated (VLP-32C)"),
        ("kitti_object", "kitti-object-000008", [0], "uncalibrated (HDL-64E, gain 1)"),
        ("kitti_raw", "kitti-raw-2011_09_26-udacity", [0], "uncalibrated (HDL-64E, gain 1)")]
GROUND_M = 0.15
MIN_RETURNS = 30


def measure(ds, samples: list[int]) -> dict[str, dict]:
    """Class name -> {returns, boxes, median, q25, q75} of the returns' reflectance estimates."""
    smp = [ds[i] for i in samples]
    acc = accumulate(smp)
    normals, _ = surface_patches(acc.points, acc.sensor)
    rho = return_reflectance(acc, np.arange(len(acc)), normals)
    ok = np.isfinite(rho)
    ground = height_above_ground(acc.points) < GROUND_M
    groups = {}
    for lab in np.unique(acc.labels[acc.labels > 0]):
        groups[LABEL_NAMES[lab]] = (acc.labels == lab) & ok
    groups["ground (unlabelled)"] = ground & (acc.labels == 0) & ok
    groups["above ground, unlabelled"] = ~ground & (acc.labels == 0) & ok
    boxes = {}
    for s in smp:
        for b in s.boxes:
            boxes[LABEL_NAMES[b.label]] = boxes.get(LABEL_NAMES[b.label], 0) + 1
    out = {}
    for name, sel in groups.items():
        v = rho[sel]
        if v.size < MIN_RETURNS:
            continue
        q25, med, q75 = np.percentile(v, [25, 50, 75])
        out[name] = {"returns": int(v.size), "boxes": boxes.get(name, 0), "median": float(med), "q25": float(q25),
                     "q75": float(q75)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args(argv)
    report = {}
    for dataset, folder, samples, scale in LOGS:
        root = args.data / folder
        if not root.exists():
            print(f"{dataset}: {root} absent, skipped")
            continue
        res = measure(open_dataset(dataset, root), samples)
        report[dataset] = {"scale": scale, "samples": samples, "classes": res}
        print(f"\n{dataset} samples {samples} ({scale}):")
        print(f"  {'class':28s} {'returns':>8s} {'boxes':>6s} {'median':>7s} {'q25':>6s} {'q75':>6s}")
        for name, m in sorted(res.items(), key=lambda kv: -kv[1]["returns"]):
            print(f"  {name:28s} {m['returns']:8d} {m['boxes']:6d} {m['median']:7.3f} {m['q25']:6.3f} {m['q75']:6.3f}")
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
