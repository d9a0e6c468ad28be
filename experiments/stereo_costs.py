"""Plane-sweep matching costs on the worlds and on KITTI-360: census against plain intensity.

One camera, two instants (issues 42/43): the reference at T and a source two frames earlier
(T - 0.2 s at 10 Hz), and a second configuration with two sources (T - 2 and T + 2 frames, their
costs averaged where both see the pixel: `reconstruct.stereo.combine_costs`). Each cost (`reconstruct.stereo.sweep_cost`:
'ad' absolute grey difference, 'ncc' 1 - zero-mean NCC, 'census' Hamming distance of the census
on the warped image, and 'census_source' the census of the source warped by nearest sampling,
the alternative `reconstruct.stereo.sweep` did not choose) with the same 7 x 7 window (the census transform's
and every cost's aggregation window) over the same 128 hypotheses uniform in inverse depth from
2 m to 90 m (0.5 m would spend three quarters of them below 2 m), then winner-take-all depth
with the parabola refinement.

Data:
- worlds: the test split's first `--worlds` worlds (styles urban, suburban, intersection,
  boulevard), the waymo-5 FRONT camera without its lens distortion (the sweep is pinhole: the
  rig's camera is re-rendered as a pinhole one at the datasets' 0.25 image scale, 480 x 320),
  rendered by `worlds.dataset.render_frames` (the worlds' textures as they are when this runs),
  reference at T = 0.2 s. Ground truth: the renderer's depth of the reference (camera z) on
  pixels that are not sky; objects: pixels that are neither sky nor ground
  (`labels.GROUND_LABEL_NAMES`). Actors move between the instants: their pixels break the sweep's
  static-scene assumption and count as they come out.
- KITTI-360: the 20-frame excerpt, frames `--kitti-frames` (default 6, 10, 14) with the
  context of `datasets.base.frames_with_context` (ICP-estimated poses: estimates), swept at half
  resolution (704 x 188: each full-resolution pixel takes its half-resolution pixel's depth).
  Ground truth as `scube-sim eval depth` takes it (`converter.eval.depth.ground_truth`: the LiDAR
  projected into the image, occluded returns removed); objects: returns off the LiDAR's ground
  plane.

Scored pixels: ground truth finite and in (0, 40) m. Per cost: coverage (share of those pixels
with a depth: the source must see them), and over those with a depth the median absolute error
(m), median relative error |p - g| / g and the share with max(p/g, g/p) < 1.25; per scene and
pooled over the worlds and over KITTI-360 (all pixels of the group together).

Run (1 thread, about 5 minutes on 2 shared cores, a minute of it KITTI-360's ICP):
`python -m experiments.stereo_costs --label before` (`--worlds N`, `--kitti DIR`, `--kitti-frames ...`).
Results: experiments/results/stereo_costs_<label>.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from bench.common import machine
from scube_sim.atomic import atomic_path
from scube_sim.camera import CameraImage, load_rig, render_camera
from scube_sim.converter.eval.depth import ground_truth
from scube_sim.datasets import open_dataset
from scube_sim.datasets.base import frames_with_context
from scube_sim.labels import GROUND_LABEL_NAMES, LABEL_IDS
from scube_sim.raytrace import Tracer
from scube_sim.reconstruct.stereo import combine_costs, inverse_depth_hypotheses, sweep_cost, winner_take_all
from scube_sim.transforms import invert_pose
from scube_sim.worlds import DatasetConfig, generate_world, sample_world_config
from scube_sim.worlds.dataset import render_frames

from .common import RESULTS

COSTS = ("ad", "ncc", "census", "census_source")
WINDOW = 7
HYPOTHESES = 128
NEAR_M, FAR_M = 2.0, 90.0
MAX_GT_M = 40.0
WORLD_SCALE = 0.25  # the datasets' image scale
WORLD_T_REF = 0.2  # seconds: sources at T - 0.2 and T + 0.2 (two frames at 10 Hz)
FRAME_S = 0.1
KITTI_DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti360-2013_05_28-seq"
KITTI_SCALE = 0.5
GROUND_IDS = np.array([LABEL_IDS[n] for n in GROUND_LABEL_NAMES])
SKY_ID = LABEL_IDS["sky"]
SOURCE_SETS = {"T-2": (-2,), "T-2,T+2": (-2, 2)}
OFFSETS = sorted({o for offs in SOURCE_SETS.values() for o in offs})
HEADER = ["group", "sources", "cost", "part", "gt_pixels", "coverage", "median_abs_err_m", "median_rel",
          "delta_1.25", "seconds"]


# --- one reference, its sources: depth per cost ---------------------------------------------------


def _tensor(rgb: np.ndarray) -> torch.Tensor:
    """(H, W, 3) uint8 -> (3, H, W) float32 in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))).to(torch.float32) / 255.0


def sweep_depths(ref: CameraImage, sources: dict[int, CameraImage]) -> dict[tuple[str, str], tuple]:
    """(source set, cost) -> (depth (H, W) float32 metres, NaN where none; seconds) for each source
    set of SOURCE_SETS whose offsets `sources` has, each cost of COSTS."""
    depths = inverse_depth_hypotheses(NEAR_M, FAR_M, HYPOTHESES)
    img = _tensor(ref.image)
    out = {}
    for cost in COSTS:
        volumes, seconds = {}, {}
        for off, src in sources.items():
            t0 = time.perf_counter()
            ref_to_src = invert_pose(src.cam_to_world) @ ref.cam_to_world
            volumes[off] = sweep_cost(img, _tensor(src.image), ref.intrinsics.K, src.intrinsics.K, ref_to_src, depths,
                                      cost=cost, window=WINDOW)
            seconds[off] = time.perf_counter() - t0
        for name, offs in SOURCE_SETS.items():
            if all(o in volumes for o in offs):
                t0 = time.perf_counter()
                depth, _, _ = winner_take_all(combine_costs([volumes[o] for o in offs]), depths)
                out[(name, cost)] = (depth.numpy(), sum(seconds[o] for o in offs) + time.perf_counter() - t0)
    return out


# --- the worlds -----------------------------------------------------------------------------------


def pinhole_front_rig(folder: Path) -> Path:
    """waymo-5's FRONT camera without its lens distortion, as a rig file (`render_frames` takes a path)."""
    front = load_rig("waymo-5").camera("FRONT").model_dump(mode="json")
    front["distortion"] = {"model": "pinhole", "coeffs": []}
    path = folder / "front-pinhole.yaml"
    path.write_text(json.dumps({"name": "front-pinhole", "notes": "waymo-5 FRONT, pinhole", "cameras": [front]}))
    return path


def world_scenes(count: int, folder: Path, camera_effects: bool = True):
    """Per world of the test split: (name, reference image, {offset: source image}, gt depth
    (H, W), objects (H, W) bool); the images at the rig's pinhole FRONT, WORLD_SCALE, with the
    datasets' exposure and vignetting unless `camera_effects` is False."""
    rig = pinhole_front_rig(folder)
    cfg = DatasetConfig()
    for i in range(count):
        world = generate_world(sample_world_config("test", i, cfg))
        shots = {k: render_frames(world, str(rig), WORLD_T_REF + k * FRAME_S, image_scale=WORLD_SCALE,
                                  camera_effects=camera_effects).images[0]
                 for k in (0, *OFFSETS)}
        ref = shots.pop(0)
        truth = render_camera([Tracer(world.mesh_at(ref.timestamp))], ref.intrinsics, ref.cam_to_world,
                              sun_dir=world.sun_dir, shading=False)
        sky = truth["sky"] | (truth["semantic"] == SKY_ID)
        gt = np.where(sky, np.inf, truth["depth"]).astype(np.float32)
        objects = ~sky & ~np.isin(truth["semantic"], GROUND_IDS)
        yield f"world {i} ({world.config.style})", ref, shots, gt, objects


# --- KITTI-360 ------------------------------------------------------------------------------------


def _half(im: CameraImage) -> CameraImage:
    intr = im.intrinsics.scaled(KITTI_SCALE)
    rgb = np.asarray(Image.fromarray(im.image).resize((intr.width, intr.height), Image.BOX))
    return CameraImage(im.name, rgb, intr, im.cam_to_world, im.timestamp)


def kitti_scenes(root: Path, frames: list[int]):
    """Per frame: (name, half-resolution reference, {offset: half-resolution source}, full-resolution
    LiDAR depth (H, W), objects = LiDAR returns off the ground plane (H, W) bool)."""
    ds = open_dataset("kitti360", root)
    for i in frames:
        fr = frames_with_context(ds, i, max(abs(o) for o in OFFSETS))
        gt, ground, _ = ground_truth(ds[i])[0]
        sources = {c.offset: _half(c.images[0]) for c in fr.context if c.offset in OFFSETS}
        yield f"kitti360 {fr.metadata.get('sample', i)}", _half(fr.images[0]), sources, gt, ~ground


def _full_resolution(depth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A half-resolution map -> each full-resolution pixel takes its half-resolution pixel's value."""
    k = round(1 / KITTI_SCALE)
    up = depth.repeat(k, 0).repeat(k, 1)
    if up.shape != shape:
        raise ValueError(f"half-resolution depth {depth.shape} does not tile the image {shape}")
    return up


# --- scoring --------------------------------------------------------------------------------------


def errors(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict:
    """Per scored pixel (gt finite, in (0, MAX_GT_M) m, in `mask`): gt and pred (NaN: none)."""
    sel = mask & np.isfinite(gt) & (gt > 0) & (gt < MAX_GT_M)
    return {"gt": gt[sel].astype(np.float64), "pred": pred[sel].astype(np.float64)}


def summary(parts: list[dict]) -> dict:
    gt = np.concatenate([p["gt"] for p in parts])
    pred = np.concatenate([p["pred"] for p in parts])
    has = np.isfinite(pred) & (pred > 0)
    p, g = pred[has], gt[has]
    err = np.abs(p - g)
    nan = float("nan")
    return {"gt_pixels": len(gt), "coverage": float(has.mean()) if len(gt) else nan,
            "median_abs_err_m": float(np.median(err)) if len(p) else nan,
            "median_rel": float(np.median(err / g)) if len(p) else nan,
            "delta_1.25": float((np.maximum(p / g, g / p) < 1.25).mean()) if len(p) else nan}


def measure(n_worlds: int, kitti_root: Path | None, kitti_frames: list[int], camera_effects: bool = True) -> list[dict]:
    torch.set_num_threads(1)  # the machine is shared; and the sweep is deterministic whatever the count
    per_scene, pooled = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        scenes = [("worlds", s) for s in world_scenes(n_worlds, Path(tmp), camera_effects)]
        if kitti_root is not None:
            scenes += [("kitti360", s) for s in kitti_scenes(kitti_root, kitti_frames)]
        for group, (name, ref, sources, gt, objects) in scenes:
            t0 = time.perf_counter()
            results = sweep_depths(ref, sources)
            print(f"{name}: swept in {time.perf_counter() - t0:.0f} s", flush=True)
            for (sset, cost), (depth, seconds) in results.items():
                if depth.shape != gt.shape:
                    depth = _full_resolution(depth, gt.shape)
                for part, mask in (("all", np.ones_like(objects)), ("objects", objects)):
                    e = errors(depth, gt, mask)
                    pooled.setdefault((group, sset, cost, part), []).append(e)
                    per_scene.append({"group": name, "sources": sset, "cost": cost, "part": part,
                                      **summary([e]), "seconds": seconds})
    rows = [{"group": f"{g} (pooled)", "sources": s, "cost": c, "part": p, **summary(v)}
            for (g, s, c, p), v in pooled.items()]
    key = {c: i for i, c in enumerate(COSTS)}
    rows.sort(key=lambda r: (r["group"], r["part"], r["sources"], key[r["cost"]]))
    return rows + per_scene


# --- output ---------------------------------------------------------------------------------------


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.3g}" if np.isfinite(v) else "–"
    return str(v)


def markdown(label: str, rows: list[dict], notes: str) -> str:
    lines = [f"# stereo_costs_{label}", "", f"machine: {machine()}", "", notes, "",
             "| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    lines += ["| " + " | ".join(_fmt(r.get(h, "")) for h in HEADER) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def write(label: str, rows: list[dict], notes: str, results: Path = RESULTS) -> Path:
    """results/stereo_costs_<label>.json and .md, each written atomically."""
    def clean(v):
        return None if isinstance(v, float) and not np.isfinite(v) else v

    doc = {"machine": machine(), "notes": notes, "rows": [{k: clean(v) for k, v in r.items()} for r in rows]}
    with atomic_path(results / f"stereo_costs_{label}.json") as tmp:
        tmp.write_text(json.dumps(doc, indent=1))
    md = results / f"stereo_costs_{label}.md"
    with atomic_path(md) as tmp:
        tmp.write_text(markdown(label, rows, notes))
    return md


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", required=True, help="names the results: stereo_costs_<label>.{json,md}")
    ap.add_argument("--worlds", type=int, default=4, help="the first N worlds of the test split")
    ap.add_argument("--kitti", type=Path, default=KITTI_DEFAULT, help="the KITTI-360 excerpt's folder")
    ap.add_argument("--kitti-frames", type=int, nargs="*", default=[6, 10, 14], help="reference frames (none: skip)")
    ap.add_argument("--no-camera-effects", action="store_true",
                    help="render the worlds through an ideal camera (no exposure gain, no vignetting)")
    args = ap.parse_args(argv)
    kitti = args.kitti if args.kitti_frames and args.kitti.is_dir() else None
    if kitti is None and args.kitti_frames:
        print(f"{args.kitti}: absent, KITTI-360 skipped")
    t0 = time.perf_counter()
    rows = measure(args.worlds, kitti, args.kitti_frames, camera_effects=not args.no_camera_effects)
    notes = (f"label {args.label}: {HYPOTHESES} hypotheses uniform in 1/depth over {NEAR_M:g}-{FAR_M:g} m, "
             f"{WINDOW}x{WINDOW} window for every cost, winner-take-all with parabola refinement; scored: ground "
             f"truth in (0, {MAX_GT_M:g}) m (worlds: not sky; objects: not sky, not ground; KITTI-360: LiDAR, "
             f"objects off the ground plane, ICP poses); worlds {WORLD_SCALE:g} scale pinhole FRONT at "
             f"T = {WORLD_T_REF:g} s, KITTI-360 swept at {KITTI_SCALE:g} scale, frames {args.kitti_frames if kitti else []}; "
             f"sources T-2 alone or T-2 and T+2 averaged; worlds camera effects (exposure, vignetting) "
             f"{'off' if args.no_camera_effects else 'on where the worlds have them'}; 1 thread, "
             f"{time.perf_counter() - t0:.0f} s in all")
    path = write(args.label, rows, notes)
    print(path.read_text())


if __name__ == "__main__":
    main()
