"""The converter measured end to end on the worlds' held-out split: camera frames -> converted
VoxSplat -> LiDAR, against the same LiDAR on the world's exact mesh (`scube-sim eval
sensor-to-sensor`).

Each sample's world is regenerated from its ``meta.json`` (the generator is deterministic in its
config and seed; the stored chunk pose is checked against the regenerated one). Three scenes are
swept with the same rays from the same poses: the world's mesh at the frames' instant (the
reference), the ground-truth VoxSplat fitted to that mesh at `gt_voxel` metres (the
representation's own error: the upper bound any converter meets) and the converted VoxSplat (its
own trace mode, metadata ``trace_mode``). Poses: the sensor on the ego at the input instant and
moved `ahead` metres along the ego's heading (the paper's LiDAR simulation drives forward through
the converted scene). Straight ahead is not where the road goes where it bends: a pose can stand
inside or against a building. So the rows are also given over the poses a car can stand at
(`pose_clear`: the ego's box and 1 m around it free of the truth's objects). The sensor model is
geometric: no range noise, no drops, strongest return, no ego-body box, so the figures are the
scenes', not the sensor's.

Rays compared: those whose mesh return lies inside the converted chunk (0.5 m in from its faces).
Seen / unseen: whether the mesh return's fine ground-truth voxel was seen by an input camera
(the dataset's ``fine_visible``, from the input cameras' depth maps), independent of the
prediction; seen-obj / seen-gnd: the seen rays whose voxel's label is not / is a ground class
(`GROUND_LABEL_NAMES`); unseen-obj / unseen-gnd: the same for the unseen rays. A converter with
a completion (`model.completion`) is also scored without it, on the same measurement: the scene
"evidence alone". Chamfer: the mean of the two directed mean nearest-neighbour distances between the
two sweeps' points inside the chunk (metres).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from ...camera.resize import resize_bilinear
from ...camera.rig import load_rig
from ...config import json_loads
from ...errors import InputError
from ...labels import GROUND_LABEL_NAMES, LABEL_IDS, NUM_LABELS
from ...lidar.compare import fidelity_config, sweep_agreement
from ...lidar.config import Drop, load_lidar_config
from ...lidar.model import Lidar
from ...memory import peak_mb, reset_peak
from ...model.completion.features import FEATURES
from ...model.geometry.metrics import chamfer_voxels, voxel_iou
from ...model.nn.image_metrics import psnr
from ...model.nn.label_metrics import semantic_metrics
from ...model.nn.lifting import LiftGrid, grid_in_box
from ...model.nn.views import render_rig
from ...raytrace.tracer import HardMode, SoftMode, Tracer
from ...transforms import invert_pose, transform_points
from ...voxsplat import VoxSplat, voxel_keys
from ...worlds.generator import WorldConfig, generate_world
from ...worlds.groundtruth import CHUNK_CORNER, CHUNK_SIZE, gt_voxsplat
from ...worlds.textures import world_albedo
from ..frames import open_frames
from ..merge import CompletionConfig, CompletionGrid
from ..pipeline import Converter
from ..profile import DEFAULT_PROFILE

AHEAD_M = (0.0, 20.0, 60.0)
CHUNK_MARGIN_M = 0.5
CLEAR_MARGIN_M = 1.0  # `pose_clear`: the ego's box grown by this, sideways and lengthways
SCENES = ("ground-truth VoxSplat", "evidence alone", "converted")
SPLITS = ("all", "seen", "unseen", "seen-obj", "seen-gnd", "unseen-obj", "unseen-gnd")
_GROUND_IDS = np.array([LABEL_IDS[n] for n in GROUND_LABEL_NAMES])

__all__ = ["AHEAD_M", "SCENES", "SweepPoses", "ahead_poses", "clear_rows", "evaluate_sample", "evaluate_split",
           "SPLITS", "format_table", "geometric_lidar", "pose_clear", "seen_labels", "seen_points", "summarise_rows",
           "sweep_metrics"]


def geometric_lidar(sensor: str) -> Lidar:
    """The preset's rays and range limits without noise, drops, second returns or ego body."""
    return Lidar(fidelity_config(load_lidar_config(sensor), noise=False, drop=Drop()))


@dataclass
class SweepPoses:
    """One LiDAR pose: `ahead` metres along the ego heading; sensor-to-chunk and -world (4, 4)."""

    ahead: float
    chunk: np.ndarray
    world: np.ndarray


def ahead_poses(lidar: Lidar, chunk_to_world: np.ndarray, ahead: Sequence[float] = AHEAD_M) -> list[SweepPoses]:
    """The sensor's poses on the ego at the chunk origin and moved along its x axis (forward)."""
    out = []
    for d in ahead:
        ego = np.eye(4)
        ego[0, 3] = float(d)
        chunk = lidar.sensor_pose(ego)
        out.append(SweepPoses(float(d), chunk, np.asarray(chunk_to_world, np.float64) @ chunk))
    return out


def pose_clear(voxels: dict, ahead: float, margin: float = CLEAR_MARGIN_M) -> bool:
    """Whether a car can stand `ahead` metres along the chunk's x axis, where `ahead_poses` puts the
    sensor: no object voxel (not ground) of the truth (`voxels.npz`: coarse_ijk from `CHUNK_CORNER`,
    coarse_labels, coarse_voxel_size) inside the ego's box there (`CompletionConfig.ego_box_min` /
    `max`, chunk frame, the road at z 0) grown by `margin` metres sideways and lengthways. The pose
    goes straight along the ego's heading, and where the road bends it can stand inside or against a
    building, whose rays say little about a scene a car drives through."""
    lo = np.array(CompletionConfig.model_fields["ego_box_min"].default) + [ahead - margin, -margin, 0.0]
    hi = np.array(CompletionConfig.model_fields["ego_box_max"].default) + [ahead + margin, margin, 0.0]
    objects = ~np.isin(np.asarray(voxels["coarse_labels"], np.int64), _GROUND_IDS)
    ijk = np.asarray(voxels["coarse_ijk"], np.int64)[objects]
    centres = CHUNK_CORNER + (ijk + 0.5) * float(voxels["coarse_voxel_size"])
    return not bool(np.any(np.all((centres >= lo) & (centres <= hi), axis=1)))


def clear_rows(samples: list[dict]) -> list[dict]:
    """The samples' rows of the poses a car can stand at (each sample's ``pose_clear``), summarised
    as `summarise_rows` does."""
    return summarise_rows([{"rows": [r for r in s["rows"] if s["pose_clear"][f"{r['ahead_m']:g}"]]}
                           for s in samples])


def _mean_nn(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    if len(a) == 0 or len(b) == 0:
        return float("nan")
    return float(cKDTree(b).query(a, k=1)[0].mean())


def sweep_metrics(ref_img: np.ndarray, cand_img: np.ndarray, rays: np.ndarray, ref_xyz: np.ndarray,
                  cand_xyz: np.ndarray) -> dict:
    """A candidate sweep against the reference over the rays `rays` (rings, columns) bool where
    the reference returns: median / p90 |range error| (m) where both return, hit agreement (share
    of `rays` the candidate returns too), Chamfer (m) between the point sets (N, 3) given."""
    return {**sweep_agreement(ref_img, cand_img, rays),
            "chamfer_m": 0.5 * (_mean_nn(ref_xyz, cand_xyz) + _mean_nn(cand_xyz, ref_xyz))}


def _inside_chunk(p_chunk: np.ndarray) -> np.ndarray:
    lo = CHUNK_CORNER + CHUNK_MARGIN_M
    hi = CHUNK_CORNER + CHUNK_SIZE * np.array([1.0, 1.0, 0.25]) - CHUNK_MARGIN_M
    return np.all((p_chunk >= lo) & (p_chunk < hi), axis=1)


def point_labels(p_chunk: np.ndarray, voxels: dict) -> tuple[np.ndarray, np.ndarray]:
    """((N,) int16 the label of each chunk-frame point's fine ground-truth voxel, -1 where it falls
    in none; (N,) bool whether an input camera saw that voxel)."""
    size = float(voxels["fine_voxel_size"])
    vis = np.asarray(voxels["fine_visible"], bool)
    keys_gt = voxel_keys(voxels["fine_ijk"])
    labels = np.asarray(voxels["fine_labels"]) if "fine_labels" in voxels else np.zeros(len(keys_gt), np.uint8)
    order = np.argsort(keys_gt)
    keys_gt, labels, vis = keys_gt[order], labels[order], vis[order]
    keys = voxel_keys(np.floor((p_chunk - CHUNK_CORNER) / size).astype(np.int64))
    out = np.full(len(keys), -1, np.int16)
    seen = np.zeros(len(keys), bool)
    if len(keys_gt):
        pos = np.minimum(np.searchsorted(keys_gt, keys), len(keys_gt) - 1)
        hit = keys_gt[pos] == keys
        out[hit] = labels[pos[hit]]
        seen[hit] = vis[pos[hit]]
    return out, seen


def seen_labels(p_chunk: np.ndarray, voxels: dict) -> np.ndarray:
    """(N,) int16: the label of each chunk-frame point's fine ground-truth voxel where an input
    camera saw that voxel, else -1."""
    labels, seen = point_labels(p_chunk, voxels)
    return np.where(seen, labels, np.int16(-1)).astype(np.int16)


def seen_points(p_chunk: np.ndarray, voxels: dict) -> np.ndarray:
    """Whether each chunk-frame point's fine ground-truth voxel was seen by an input camera."""
    return seen_labels(p_chunk, voxels) >= 0


def _input_psnr(scene: VoxSplat, frames, rig: str) -> float:
    """PSNR (dB) of the converted scene rendered through the sample's rig on the ego at the chunk
    origin, at the input images' scale, against the input images: how well the appearance stage
    reproduces what it saw."""
    rig_cfg = load_rig(rig)
    native = {c.name: c.intrinsics().width for c in rig_cfg.cameras}
    first = frames.images[0]
    views = render_rig(scene, rig_cfg, np.eye(4), scale=first.intrinsics.width / native[first.name])
    vals = []
    for im in frames.images:
        if im.name not in views:
            continue
        pred = torch.from_numpy(views[im.name]).permute(2, 0, 1)
        img = torch.from_numpy(np.asarray(im.image, np.float32) / (255.0 if im.image.dtype == np.uint8 else 1.0))
        gt = resize_bilinear(img.permute(2, 0, 1), pred.shape[1:])
        vals.append(psnr(pred[None], gt[None]))  # (1, 3, H, W)
    return float(np.mean(vals)) if vals else float("nan")


def evaluate_sample(conv: Converter, sample_dir: Path, lidar: Lidar, *, gt_voxel: float = 0.4, seed: int = 0,
                    ahead: Sequence[float] = AHEAD_M, convert_options: dict | None = None,
                    with_psnr: bool = True, gt_cache: dict | None = None,
                    trace_mode: str | HardMode | SoftMode | None = None, context: int | None = None,
                    sweeps: dict | None = None) -> dict:
    """One worlds sample (module docstring): -> {"sample", "stages": {geometry IoU, Chamfer in
    voxels, PSNR at the input cameras, seconds, peak MB, the observed Gaussians' centres to the mesh
    (median and p90 m) and the ground-truth VoxSplat's (median)}, "rows": [{scene, ahead, split, rays,
    median_m, p90_m, hit_agreement, chamfer_m}], "pose_clear": {metres ahead ("20"): whether a car can
    stand there, `pose_clear`}}. gt_cache: a dict kept across calls that holds
    each sample's regenerated world, mesh sweeps and ground-truth rows (a trade sweep over
    converter settings then regenerates nothing). trace_mode: how the converted scene is traced, a
    mode's name or options (default its metadata ``trace_mode``). context: the instants before
    and after the sample the converter sees (`open_frames`; default the profile's). sweeps: a
    dict that receives each traced scene's range image (rings, columns; NaN: no return) by
    (scene, metres ahead), to compare scenes ray by ray."""
    sample_dir = Path(sample_dir)
    meta = json_loads((sample_dir / "meta.json").read_text(), sample_dir / "meta.json", InputError)
    key = str(sample_dir.resolve())
    cached = gt_cache.get(key) if gt_cache is not None else None
    if cached is None:
        cached = _reference(sample_dir, meta, lidar, gt_voxel=gt_voxel, seed=seed, ahead=ahead)
        if gt_cache is not None:
            gt_cache[key] = cached
    context = conv.profile.context if context is None else context
    frames = open_frames(sample_dir, context=context)
    reset_peak()
    t0 = time.perf_counter()
    done = conv.convert(frames, seed=seed, **(convert_options or {}))
    scene = done.scene
    seconds = time.perf_counter() - t0
    # the route's own stages (the paper's: geometry_s, appearance_s; evidence: stereo_s, fusion_s, completion_s)
    stages = {"seconds": seconds, **{k: v for k, v in done.timings.items() if k.endswith("_s")}, "peak_mb": peak_mb()}
    ijk = scene.ijk
    vox = cached["voxels"]
    gt_ijk = vox["coarse_ijk"].astype(np.int64)
    if abs(scene.voxel_size - float(vox["coarse_voxel_size"])) < 1e-9:
        stages["geometry_iou"] = voxel_iou(ijk, gt_ijk)
        stages["geometry_chamfer_vox"] = chamfer_voxels(ijk, gt_ijk)
    # the surfaces the cameras saw against the mesh: each observed Gaussian's centre to its nearest point
    obs = _surface_distance(scene, cached["mesh"], observed_only=True)
    if obs.size:
        stages["surface_median_m"], stages["surface_p90_m"] = float(np.median(obs)), float(np.percentile(obs, 90))
    stages["gt_surface_median_m"] = cached["gt_surface_median_m"]
    if with_psnr and "sky_panorama" in scene.channels:
        stages["input_psnr_db"] = _input_psnr(scene, frames, meta["rig"])
    tracer = Tracer(scene, trace_mode or scene.metadata.get("trace_mode", "entry"))
    t1 = time.perf_counter()
    rows = list(cached["rows"])
    if done.completion_grid is not None:
        stages.update(completion_grid_metrics(done.completion_grid, vox))
        merged = scene.metadata.get("completion", {})
        stages["completion_added_cells"] = float(merged.get("added_cells", 0))
        stages["completion_removed_share"] = merged.get("removed_voxels", 0) / max(merged.get("observed_voxels", 0), 1)
    # with a completion: the same measurement without it, traced from the same poses
    alone = done.uncompleted
    alone_tracer = None if alone is None else Tracer(alone, trace_mode or alone.metadata.get("trace_mode", "entry"))
    for ref, p in zip(cached["refs"], cached["poses"]):
        traced = {"converted": lidar.scan(tracer, p.chunk, seed=seed)}
        if alone_tracer is not None:
            traced[SCENES[1]] = lidar.scan(alone_tracer, p.chunk, seed=seed)
        for name, sweep in traced.items():
            rows += _rows(name, p.ahead, ref, sweep, p.chunk)
            if sweeps is not None:
                sweeps[(name, p.ahead)] = sweep.range_image()
    stages["trace_s_per_sweep"] = (time.perf_counter() - t1) / max(len(cached["poses"]), 1)
    # the context asked for and the instants the converter was given (fewer where the log has fewer)
    return {"sample": f"{sample_dir.parent.name}/{sample_dir.name}", "context": context,
            "offsets": [0] + [c.offset for c in frames.context], "stages": stages, "rows": rows,
            "pose_clear": {f"{p.ahead:g}": pose_clear(vox, p.ahead) for p in cached["poses"]},
            "voxels": len(ijk), "observed_fraction": float(np.mean(scene.channel("observed")))}


def completion_grid_metrics(grid: CompletionGrid, voxels: dict) -> dict:
    """The completion's coarse grid (`Conversion.completion_grid`) against the ground truth's coarse
    voxels coarsened to it (occupied if any child is, the most frequent label): IoU of the cells at
    p >= 0.5, mIoU of their labels (over the labels present in the truth or the prediction, on
    the cells both hold), and the evidence alone's IoU (the cells holding an observed voxel)."""
    vs, occ, lab = float(grid.voxel_size), grid.occupancy >= 0.5, grid.labels
    stored = float(voxels["coarse_voxel_size"])
    factor = int(round(vs / stored))
    box = LiftGrid(tuple(float(v) for v in grid.corner), vs, tuple(int(d) for d in occ.shape))
    rel, labels, _ = grid_in_box(torch.from_numpy(voxels["coarse_ijk"].astype(np.int64)),
                                 torch.from_numpy(voxels["coarse_labels"].astype(np.int64)),
                                 torch.from_numpy(np.asarray(voxels["coarse_visible"], bool)), factor, stored, box)
    rel, labels = rel.numpy(), labels.numpy()
    gt = np.zeros(occ.shape, bool)
    gt[rel[:, 0], rel[:, 1], rel[:, 2]] = True
    gt_lab = np.full(occ.shape, -1, np.int64)
    gt_lab[rel[:, 0], rel[:, 1], rel[:, 2]] = labels
    evidence = grid.features[FEATURES.index("occupied")] > 0
    both = occ & gt
    n = NUM_LABELS
    conf = np.bincount(gt_lab[both] * n + lab[both], minlength=n * n).reshape(n, n)
    iou = lambda a: float((a & gt).sum() / max((a | gt).sum(), 1))  # noqa: E731
    return {"completion_iou": iou(occ), "completion_miou": semantic_metrics(torch.from_numpy(conf))["miou"],
            "evidence_iou": iou(evidence)}


def _reference(sample_dir: Path, meta: dict, lidar: Lidar, *, gt_voxel: float, seed: int,
               ahead: Sequence[float]) -> dict:
    """The world regenerated, its mesh sweeps and the ground-truth VoxSplat's rows."""
    if meta.get("format") != "scube_sim.worlds" or "world" not in meta:
        raise InputError(f"{sample_dir / 'meta.json'}: not a worlds sample (format scube_sim.worlds with a world key)")
    world = generate_world(WorldConfig(**meta["world"]))
    chunk_to_world = np.asarray(meta["chunk_to_world"], np.float64)
    # the input instant T (offset 0; from dataset version 3 on, instants before it come first)
    t = next((float(f.get("time", 0.0)) for f in meta.get("frames", []) if f.get("offset", 0) == 0), 0.0)
    if not np.allclose(world.ego_pose_at(t), chunk_to_world, atol=1e-6):
        raise InputError(f"{sample_dir}: the regenerated world's ego pose differs from meta.json's chunk_to_world "
                         f"(generator version {meta.get('world_version')}): regenerate the dataset")
    mesh = world.mesh_at(t)
    with np.load(sample_dir / "voxels.npz") as z:
        voxels = {k: z[k] for k in z.files}
    gt = gt_voxsplat(mesh, chunk_to_world, gt_voxel, albedo_fn=world_albedo(world, t))
    mesh_tracer, gt_tracer = Tracer(mesh), Tracer(gt, mode="entry")
    poses = ahead_poses(lidar, chunk_to_world, ahead)
    refs, rows = [], []
    to_chunk = invert_pose(chunk_to_world)
    for p in poses:
        m = lidar.scan(mesh_tracer, p.world, seed=seed)
        pts = transform_points(to_chunk @ p.world, m.xyz().astype(np.float64))
        rr, cc = m.pixels()
        inside = _inside_chunk(pts)
        lab, seen = point_labels(pts, voxels)
        ground = np.isin(lab, _GROUND_IDS)
        img_shape = (m.channels, m.columns)
        sels = {"all": inside, "seen": inside & seen, "unseen": inside & ~seen,
                "seen-obj": inside & seen & ~ground, "seen-gnd": inside & seen & ground,
                "unseen-obj": inside & ~seen & ~ground, "unseen-gnd": inside & ~seen & ground}
        masks = {}
        for name, sel in sels.items():
            mk = np.zeros(img_shape, bool)
            mk[rr[sel], cc[sel]] = True
            masks[name] = mk
        ref = {"img": m.range_image(), "masks": masks, "xyz": {k: pts[sel] for k, sel in sels.items()}}
        refs.append(ref)
        rows += _rows(SCENES[0], p.ahead, ref, lidar.scan(gt_tracer, p.chunk, seed=seed), p.chunk)
    return {"voxels": voxels, "poses": poses, "refs": refs, "rows": rows, "gt_gaussians": gt.num_gaussians,
            "mesh": mesh, "gt_surface_median_m": float(np.median(_surface_distance(gt, mesh)))}


def _surface_distance(scene: VoxSplat, mesh, observed_only: bool = False) -> np.ndarray:
    """(N,) metres from the scene's Gaussian centres (those of observed voxels only, where asked and
    the scene has the channel) to the mesh; the scene in its chunk frame (metadata ``chunk_to_world``)."""
    g = scene.gaussians()
    keep = np.ones(len(g.means), bool)
    if observed_only and "observed" in scene.channels:
        keep = np.asarray(scene.channels["observed"].data, bool)[g.voxel]
    c2w = np.asarray(scene.metadata["chunk_to_world"], np.float64)
    return mesh.distance(transform_points(c2w, g.means[keep].astype(np.float64) + scene.origin))


def _rows(scene: str, ahead: float, ref: dict, sweep, pose_chunk: np.ndarray) -> list[dict]:
    img = sweep.range_image()
    pts = transform_points(pose_chunk, sweep.xyz().astype(np.float64))
    rr, cc = sweep.pixels()
    inside = _inside_chunk(pts)
    out = []
    for split, mask in ref["masks"].items():
        # the candidate's points on the split's rays (its own returns there, wherever they land)
        on = mask[rr, cc] & inside
        m = sweep_metrics(ref["img"], img, mask, ref["xyz"][split], pts[on])
        out.append({"scene": scene, "ahead_m": ahead, "split": split, **m})
    return out


def summarise_rows(samples: list[dict]) -> list[dict]:
    """Per (scene, ahead, split): the ray-weighted means of the samples' figures (median and p90
    are per-sample figures averaged, weighted by their rays)."""
    groups: dict[tuple, list[dict]] = {}
    for s in samples:
        for r in s["rows"]:
            groups.setdefault((r["scene"], r["ahead_m"], r["split"]), []).append(r)
    out = []
    for (scene, ahead, split), rs in groups.items():
        w = np.array([r["rays"] for r in rs], np.float64)
        row = {"scene": scene, "ahead_m": ahead, "split": split, "rays": int(w.sum())}
        for k in ("median_m", "p90_m", "hit_agreement", "chamfer_m"):
            v = np.array([r[k] for r in rs], np.float64)
            ok = np.isfinite(v) & (w > 0)
            row[k] = float(np.average(v[ok], weights=w[ok])) if ok.any() else float("nan")
        out.append(row)
    order = {s: i for i, s in enumerate(SCENES)}
    return sorted(out, key=lambda r: (r["ahead_m"], SPLITS.index(r["split"]),
                                      order.get(r["scene"], 99)))


def evaluate_split(data: Path, *, split: str = "test", profile=DEFAULT_PROFILE, sensor: str = "hdl64e", limit: int | None = None,
                   gt_voxel: float = 0.4, seed: int = 0, ahead: Sequence[float] = AHEAD_M,
                   convert_options: dict | None = None, with_psnr: bool = True,
                   progress: Callable | None = None, context: int | None = None) -> dict:
    """`evaluate_sample` over a worlds split (the first `limit` samples) -> {"rows": summarised,
    "clear_poses": per distance ahead the samples whose pose there a car can stand at (`pose_clear`),
    "clear_rows": the rows over those alone, "stages": means, "samples": per sample}. context: as
    `evaluate_sample`."""
    root = Path(data) / split
    if not root.is_dir():
        raise InputError(f"{root}: no such split folder (a worlds dataset: DIR/<split>/NNNNNN)")
    dirs = sorted(d for d in root.iterdir() if (d / "meta.json").is_file())
    if limit is not None:
        dirs = dirs[:limit]
    if not dirs:
        raise InputError(f"{root}: no samples")
    conv = Converter(profile)
    lidar = geometric_lidar(sensor)
    samples = []
    it = progress(dirs) if progress else dirs
    for d in it:
        samples.append(evaluate_sample(conv, d, lidar, gt_voxel=gt_voxel, seed=seed, ahead=ahead,
                                       convert_options=convert_options, with_psnr=with_psnr, context=context))
    stage_keys = dict.fromkeys(k for s in samples for k in s["stages"])
    stages = {k: float(np.nanmean([s["stages"].get(k, np.nan) for s in samples])) for k in stage_keys}
    stages["peak_mb"] = float(max(s["stages"]["peak_mb"] for s in samples))
    return {"split": split, "profile": conv.profile.name, "sensor": lidar.config.name, "gt_voxel_m": gt_voxel,
            "samples_n": len(samples), "rows": summarise_rows(samples),
            "clear_poses": {a: sum(s["pose_clear"][a] for s in samples) for a in samples[0]["pose_clear"]},
            "clear_rows": clear_rows(samples), "stages": stages, "samples": samples}


def _row_line(r: dict) -> str:
    return (f"{r['ahead_m']:5.0f}m {r['rays']:7d} {r['scene']:<22s} {r['split']:<8s} {r['median_m']:9.3f} m "
            f"{r['p90_m']:7.3f} m {100 * r['hit_agreement']:6.1f}% {r['chamfer_m']:6.3f} m")


def format_table(res: dict, split: str, gt_voxel: float) -> list[str]:
    """`evaluate_split`'s result as the lines `scube-sim eval sensor-to-sensor` prints: a title, one
    row per scene and distance ahead, and the stages' means per sample."""
    lines = [f"{res['samples_n']} {split} samples, profile {res['profile']}, {res['sensor']}, against the mesh; "
             f"ground-truth VoxSplat at {gt_voxel:g} m",
             f"{'ahead':>6s} {'rays':>7s} {'scene':<22s} {'split':<8s} {'median |dr|':>11s} {'p90 |dr|':>9s} "
             f"{'hits':>7s} {'Chamfer':>8s}"]
    lines += [_row_line(r) for r in res["rows"]]
    if res.get("clear_rows") and any(n < res["samples_n"] for n in res["clear_poses"].values()):
        counts = ", ".join(f"{n} at {a} m" for a, n in res["clear_poses"].items())
        lines.append(f"the poses a car can stand at ({counts} of {res['samples_n']}; pose_clear):")
        lines += [_row_line(r) for r in res["clear_rows"]]
    lines.append("stages (mean per sample): " + ", ".join(f"{k} {v:.4g}" for k, v in res["stages"].items()))
    return lines
