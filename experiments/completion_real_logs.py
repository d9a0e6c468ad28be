"""The learned completion on real logs (issue 45): the evidence-fusion issue's real-log table with
the completion on and off, on one measurement per log (the converter keeps the evidence-alone
scene it completed, `Converter.uncompleted`), and how much observed surface the completion
removed.

Per log: `Converter(profile).convert(open_frames(...)).scene` writes the completed scene and the
evidence-alone one, then `scube-sim fidelity DATA -d D --sample I --scene S --no-baselines
--ground-plane --regions` scores each against the real sweep of the same instant (the returns
within 40 m inside the cameras' view, ground and above ground apart); the figures are read from
its report.json. Removed share: the observed voxels the merge dropped over those the evidence held
(a confident one, fused probability >= keep_confidence, is never dropped by construction).

    python -m experiments.completion_real_logs [--profile evidence-complete] [--logs k360-10,kitti-1] [-o DIR]

A profile without a completion (`--profile evidence`) scores its scene alone, into
results/real_logs_<profile>.{json,md}; logs other than the default set add their names to the file's
(`--logs tri-2`: results/real_logs_evidence_tri-2).

Logs (`LOGS`): KITTI-360 frames 3004 / 3010 / 3015 of the excerpt (context 4), KITTI raw frame 1
(context 1), the nuScenes demo keyframe (no context); TRI (538 s and 4.4 GB a conversion) only when
named. Data: ../shared/data next to the repository.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from experiments.common import write_results

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
LOGS = {  # name: (folder, dataset, sample, context, more fidelity options)
    "k360-4": ("kitti360-2013_05_28-seq", "kitti360", 4, 4, []),
    "k360-10": ("kitti360-2013_05_28-seq", "kitti360", 10, 4, []),
    "k360-15": ("kitti360-2013_05_28-seq", "kitti360", 15, 4, []),
    "kitti-1": ("kitti-raw-2011_09_26-udacity", "kitti_raw", 1, 1, []),
    "nuscenes-0": ("nuscenes-mmdet3d-demo", "nuscenes", 0, 0, []),
    # a merged cloud: surface distances only
    "tri-2": ("tri-dgp-test-scene_02", "tri_dgp", 2, 2, ["--assume-single-origin"]),
}
DEFAULT_LOGS = ["k360-4", "k360-10", "k360-15", "kitti-1", "nuscenes-0"]
REGIONS = {"above": "voxsplat [camera view, above ground]", "ground": "voxsplat [camera view, ground]"}


def _fidelity(folder: Path, dataset: str, sample: int, scene: Path, out: Path, more: list[str]) -> dict:
    cmd = [sys.executable, "-m", "scube_sim.cli", "fidelity", str(folder), "-d", dataset, "--sample", str(sample),
           "--scene", str(scene), "--no-baselines", "--ground-plane", "--regions", "-o", str(out), *more]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads((out / "report.json").read_text())


def _row(name: str, which: str, report: dict) -> dict:
    row = {"log": name, "scene": which}
    for key, region in REGIONS.items():
        r = report["rows"].get(region, {})
        row[f"{key}_median_m"] = r.get("median_abs_m")
        row[f"{key}_p90_m"] = r.get("p90_abs_m")
        row[f"{key}_hits"] = r.get("hit_agreement")
    # the real returns' distance to the scene's surfaces, and the plane fitted to the sweep's
    surface = report.get("surface", {})
    for key, part in (("above", "above ground"), ("ground", "ground")):
        row[f"{key}_to_surface_m"] = surface.get(f"voxsplat, {part}", {}).get("to_scene_median_m")
        row[f"{key}_plane_m"] = surface.get(f"baseline: plane fitted to the sweep, {part}", {}).get("to_scene_median_m")
    return row


def main(argv=None) -> None:
    from scube_sim.converter.frames import open_frames
    from scube_sim.converter.pipeline import Converter

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="evidence-complete")
    ap.add_argument("--logs", default=",".join(DEFAULT_LOGS))
    ap.add_argument("-o", "--output", type=Path, default=ROOT / "experiments" / ".cache" / "completion_real")
    args = ap.parse_args(argv)
    conv = Converter(args.profile)
    completes = conv.profile.completion is not None
    rows = []
    for name in [n.strip() for n in args.logs.split(",") if n.strip()]:
        folder, dataset, sample, context, more = LOGS[name]
        path = DATA / folder
        if not path.is_dir():
            print(f"{name}: {path} absent, skipped")
            continue
        out = args.output / name
        out.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        conversion = conv.convert(open_frames(path, dataset, sample, context=context))
        scene = conversion.scene
        seconds = time.perf_counter() - t0
        if completes:
            scene.save(out / "completed.npz")
            conversion.uncompleted.save(out / "evidence.npz")
            done = scene.metadata["completion"]
            scenes = (("evidence alone", "evidence.npz"), ("completed", "completed.npz"))
        else:
            scene.save(out / "scene.npz")
            scenes = ((conv.profile.name, "scene.npz"),)
        for which, file in scenes:
            row = _row(name, which, _fidelity(path, dataset, sample, out / file, out / f"fid_{file[:-4]}", more))
            if not completes:
                row["convert_s"] = seconds
            elif which == "completed":
                row.update({"added_cells": done["added_cells"], "removed_voxels": done["removed_voxels"],
                            "observed_voxels": done["observed_voxels"],
                            "removed_share": done["removed_voxels"] / max(done["observed_voxels"], 1),
                            "convert_s": seconds, "completion_s": conversion.timings.get("completion_s")})
            rows.append(row)
            print(json.dumps(row))
    header = ["log", "scene", "above_to_surface_m", "above_plane_m", "above_median_m", "above_p90_m", "above_hits", "ground_median_m", "ground_p90_m",
              "ground_hits", "removed_share", "added_cells", "convert_s"]
    notes = (f"python -m experiments.completion_real_logs --profile {args.profile} --logs {args.logs}; replayed real "
             f"rays inside the cameras' view within 40 m (fidelity --regions), above ground and on the ground")
    # other logs than the default set go to their own file, beside the default set's table
    suffix = "" if args.logs == ",".join(DEFAULT_LOGS) else "_" + args.logs.replace(",", "_")
    write_results(("completion_real_logs" if completes else f"real_logs_{conv.profile.name}") + suffix, rows, header,
                  notes)


if __name__ == "__main__":
    main()
