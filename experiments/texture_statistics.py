"""How matchable the procedural worlds' camera images are, against real photographs (issue 42).

Multi-view stereo needs texture at its own angular scale. Every image, rendered or real, is brought
to the common scale (`scube_sim.camera.texture.to_common_scale`: a focal of 500 px, about the
worlds' own) and measured per class (`class_statistics`): gradient energy, the median normalised
std in 7 x 7 and 15 x 15 windows, the share of matchable 7 x 7 windows, and the pixel count.

- **Worlds**: the first `--worlds` samples of the test split (the samples cycle through the styles,
  so 8 gives 2 per style), each rig camera at the input instant T as the datasets render it
  (`scube_sim.worlds.dataset.render_frames`: same world, rig, image scale, poses and textures as
  `make_sample`), with its per-pixel semantics. Classes by label: road (+ lane_marker),
  building, vehicle (car, truck, bus, other_vehicle), vegetation (+ tree_trunk), terrain,
  sidewalk (+ walkable); "all" is every pixel but the sky.
- **Real**: the images of ../shared/data read through the dataset adapters
  (`scube_sim.datasets.open_dataset`). They have no labels, so the classes are rectangles picked by
  eye (REGIONS below, in the adapter's image pixels); "all" is each listed image without its
  "sky" and "ignore" rectangles (the ego vehicle's own body); the rest of the sky (gaps in
  foliage, above the rectangles) stays in, so a real "all" is a little smoother than its scene.
  A missing folder is skipped with its reason printed.

A class's statistics pool the pixels of all its images (per source); "real range" is the min-max of
the per-image values over the real images (those with at least MIN_PIXELS measured pixels), and
the worlds row says of each value whether it is inside that range, low or high.

Not part of `make bench` (about 2.5 s per world on 2 cores, plus ~10 s for the real images). Run:
`python -m experiments.texture_statistics [--worlds 8] [--before | --label NAME] [--data ../shared/data]`
Results: experiments/results/texture_statistics[_<label>].{json,md} and
docs/texture_crops[_<label>].png (crops at the common scale, worlds against real, per class);
`--draw-regions DIR` writes each real image with its rectangles drawn, to check the table.
"""

from __future__ import annotations

import argparse
import hashlib
import inspect
import json
import math
import time
from pathlib import Path

import numpy as np
from rich.progress import track
from scipy import ndimage

from scube_sim.atomic import atomic_path
from scube_sim.camera import render_camera
from scube_sim.camera.texture import (
    COMMON_FOCAL_PX,
    MATCHABLE_THRESHOLD,
    summarise,
    texture_samples,
    to_common_scale,
    to_grey,
)
from scube_sim.datasets import open_dataset
from scube_sim.labels import label_id
from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace import Tracer
from scube_sim.worlds import DatasetConfig, albedo, generate_world, sample_world_config
from scube_sim.worlds.dataset import render_frames

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
STATS = ("gradient_energy", "contrast_7", "contrast_15", "matchable")
CLASSES = ("road", "building", "vehicle", "vegetation", "terrain", "sidewalk", "all")
# the classes of the crops figure, one row each
FIGURE_CLASSES = ("road", "building", "vehicle", "vegetation")
# worlds label names per class ("all": every pixel but the sky)
WORLDS_CLASSES = {
    "road": ("road", "lane_marker"),
    "building": ("building",),
    "vehicle": ("car", "truck", "bus", "other_vehicle"),
    "vegetation": ("vegetation", "tree_trunk"),
    "terrain": ("terrain",),
    "sidewalk": ("sidewalk", "walkable"),
}
# a per-image value enters the ranges only with at least this many measured pixels (at the common
# scale: ~17 x 17 interior pixels, enough for a median not to hinge on one feature)
MIN_PIXELS = 300
CROP = 96  # side of the figure's crops, pixels at the common scale

# The real sets: name -> (folder under --data, adapter, adapter options). KITTI-360's poses are not
# needed here: "identity" skips the ICP the excerpt would otherwise run (~25 s).
REAL_SETS = {
    "kitti360": ("kitti360-2013_05_28-seq", "kitti360", {"poses": "identity"}),
    "kitti_raw": ("kitti-raw-2011_09_26-udacity", "kitti_raw", {}),
    "kitti_object": ("kitti-object-000008", "kitti_object", {}),
    "nuscenes": ("nuscenes-mmdet3d-demo", "nuscenes", {}),
    "tri_dgp": ("tri-dgp-test-scene_02", "tri_dgp", {}),
    "waymo": ("waymo-open-dataset-frame", "waymo", {}),
    "argoverse2": ("argoverse2-sensor-log-7fab2350", "argoverse2", {}),
}

# Class rectangles of the real images, picked by eye: (set, sample index, camera, class, x0, y0, x1,
# y1), pixels of the adapter's image, x1 / y1 exclusive. "sky" and "ignore" (the ego vehicle's own
# body) only cut those pixels out of "all". Each rectangle lies inside one surface of its class;
# the statistics keep only pixels whose 15 x 15 window (at the common scale) lies inside it.
REGIONS = [
    # KITTI-360 2013_05_28 (1408 x 376, fx 552): hedge on the left, parked car on the right (the
    # house over the hedge is overexposed and 40 rows high: left out)
    ("kitti360", 0, "image_00", "vegetation", 20, 100, 300, 280),  # the hedge
    ("kitti360", 0, "image_00", "vegetation", 830, 20, 1000, 140),  # dark trees, right
    ("kitti360", 0, "image_00", "road", 530, 270, 760, 370),
    ("kitti360", 0, "image_00", "vehicle", 1150, 190, 1370, 250),  # the parked silver car
    ("kitti360", 0, "image_00", "sidewalk", 950, 300, 1250, 370),  # paving stones, right
    ("kitti360", 0, "image_00", "sky", 600, 0, 700, 90),
    ("kitti360", 10, "image_00", "vegetation", 20, 60, 400, 300),
    ("kitti360", 10, "image_00", "road", 500, 270, 800, 370),
    ("kitti360", 10, "image_00", "sidewalk", 900, 290, 1300, 370),  # paving in the trees' shade
    ("kitti360", 10, "image_00", "sky", 560, 0, 660, 100),
    # KITTI raw 2011_09_26 (1242 x 375, fx 721): queue of cars under a bridge
    ("kitti_raw", 0, "image_02", "vehicle", 110, 200, 380, 350),  # grey hatchback, left
    ("kitti_raw", 0, "image_02", "vehicle", 570, 200, 700, 300),  # car ahead
    ("kitti_raw", 0, "image_02", "vehicle", 830, 60, 1060, 300),  # truck cab, right
    ("kitti_raw", 0, "image_02", "road", 400, 290, 560, 370),
    ("kitti_raw", 0, "image_02", "vegetation", 0, 0, 90, 55),
    ("kitti_raw", 0, "image_02", "sky", 150, 0, 450, 35),
    # KITTI object 000008 (1242 x 375, fx 721): residential street with parked cars
    ("kitti_object", 0, "CAM2", "vehicle", 370, 200, 590, 320),  # grey car
    ("kitti_object", 0, "CAM2", "vehicle", 0, 220, 340, 375),  # red car, left
    ("kitti_object", 0, "CAM2", "vehicle", 960, 225, 1240, 375),  # dark car, right
    ("kitti_object", 0, "CAM2", "building", 350, 10, 500, 125),  # white house, left
    ("kitti_object", 0, "CAM2", "building", 665, 40, 760, 150),  # houses ahead
    ("kitti_object", 0, "CAM2", "vegetation", 10, 10, 300, 150),
    ("kitti_object", 0, "CAM2", "vegetation", 520, 60, 660, 160),
    ("kitti_object", 0, "CAM2", "road", 770, 230, 950, 370),
    ("kitti_object", 0, "CAM2", "sky", 620, 0, 900, 55),
    # nuScenes n015 keyframe (1600 x 900, fx 1266; CAM_BACK 809): Singapore, towers and trees
    ("nuscenes", 0, "CAM_FRONT", "road", 850, 640, 1350, 880),
    ("nuscenes", 0, "CAM_FRONT", "vehicle", 140, 310, 560, 540),  # the lorry's back, left
    ("nuscenes", 0, "CAM_FRONT", "building", 0, 0, 450, 200),  # glass tower, left
    ("nuscenes", 0, "CAM_FRONT", "vegetation", 560, 330, 900, 440),
    ("nuscenes", 0, "CAM_FRONT", "vegetation", 1400, 270, 1600, 410),
    ("nuscenes", 0, "CAM_FRONT", "sky", 500, 20, 1000, 150),
    ("nuscenes", 0, "CAM_FRONT_LEFT", "building", 250, 20, 1250, 360),  # the slanted columns
    ("nuscenes", 0, "CAM_FRONT_LEFT", "vegetation", 700, 460, 1300, 540),  # shrubs
    ("nuscenes", 0, "CAM_FRONT_LEFT", "terrain", 0, 650, 500, 850),  # grass
    ("nuscenes", 0, "CAM_FRONT_RIGHT", "vegetation", 0, 270, 640, 470),
    ("nuscenes", 0, "CAM_FRONT_RIGHT", "building", 880, 60, 1500, 200),  # the round tower's underside
    ("nuscenes", 0, "CAM_FRONT_RIGHT", "road", 100, 720, 900, 890),
    ("nuscenes", 0, "CAM_FRONT_RIGHT", "sky", 580, 0, 790, 230),
    ("nuscenes", 0, "CAM_BACK", "road", 300, 620, 1100, 860),
    ("nuscenes", 0, "CAM_BACK", "building", 400, 30, 700, 300),
    ("nuscenes", 0, "CAM_BACK", "building", 900, 20, 1400, 400),
    ("nuscenes", 0, "CAM_BACK", "vehicle", 340, 510, 520, 580),  # taxi
    ("nuscenes", 0, "CAM_BACK", "vegetation", 1120, 510, 1600, 640),
    ("nuscenes", 0, "CAM_BACK", "sky", 730, 0, 920, 300),
    ("nuscenes", 0, "CAM_BACK", "ignore", 0, 860, 1600, 900),  # the ego's boot
    ("nuscenes", 0, "CAM_BACK_LEFT", "building", 670, 0, 1400, 420),
    ("nuscenes", 0, "CAM_BACK_LEFT", "vegetation", 0, 400, 700, 580),
    # TRI DGP scene_02 (1936 x 1216, fx 2181 for CAMERA_01, ~1060 the others): suburban Michigan
    ("tri_dgp", 0, "CAMERA_01", "road", 300, 850, 1700, 1200),
    ("tri_dgp", 0, "CAMERA_01", "vegetation", 350, 180, 900, 520),
    ("tri_dgp", 0, "CAMERA_01", "vegetation", 1200, 250, 1500, 520),
    ("tri_dgp", 0, "CAMERA_01", "sky", 1000, 280, 1110, 500),
    ("tri_dgp", 0, "CAMERA_05", "vegetation", 60, 180, 380, 440),
    ("tri_dgp", 0, "CAMERA_05", "building", 1100, 430, 1310, 560),  # white house
    ("tri_dgp", 0, "CAMERA_05", "road", 200, 880, 1400, 1030),
    ("tri_dgp", 0, "CAMERA_05", "terrain", 0, 600, 900, 760),  # lawn
    ("tri_dgp", 0, "CAMERA_05", "sky", 0, 0, 1936, 100),
    ("tri_dgp", 0, "CAMERA_05", "ignore", 0, 1060, 1936, 1216),  # the ego's bonnet
    ("tri_dgp", 0, "CAMERA_06", "vegetation", 100, 50, 600, 400),
    ("tri_dgp", 0, "CAMERA_06", "vehicle", 720, 560, 920, 660),  # pick-up under the trees
    ("tri_dgp", 0, "CAMERA_06", "terrain", 600, 800, 1500, 1050),
    ("tri_dgp", 0, "CAMERA_06", "sky", 1300, 0, 1936, 250),
    ("tri_dgp", 0, "CAMERA_06", "ignore", 0, 1080, 1936, 1216),
    # Waymo segment 10243601... (1920 x 1280 / 886, fx ~2050): San Francisco, the waymo-5 rig itself
    ("waymo", 0, "FRONT", "road", 600, 820, 1900, 1260),
    ("waymo", 0, "FRONT", "building", 1480, 60, 1900, 440),  # brick block, right
    ("waymo", 0, "FRONT", "vegetation", 1480, 480, 1625, 575),
    ("waymo", 0, "FRONT", "vehicle", 1390, 600, 1530, 740),  # lorry cab
    ("waymo", 0, "FRONT", "sky", 300, 0, 1300, 330),
    ("waymo", 0, "FRONT_LEFT", "vehicle", 0, 700, 700, 1270),  # postal van
    ("waymo", 0, "FRONT_LEFT", "vehicle", 760, 700, 990, 850),  # dark saloon
    ("waymo", 0, "FRONT_LEFT", "sky", 650, 0, 1400, 220),
    ("waymo", 0, "FRONT_RIGHT", "building", 0, 20, 600, 430),
    ("waymo", 0, "FRONT_RIGHT", "building", 850, 300, 1450, 620),
    ("waymo", 0, "FRONT_RIGHT", "vehicle", 1000, 930, 1920, 1280),  # silver hatchback
    ("waymo", 0, "FRONT_RIGHT", "road", 0, 900, 950, 1270),
    ("waymo", 0, "FRONT_RIGHT", "vegetation", 150, 490, 550, 600),
    ("waymo", 0, "SIDE_LEFT", "vehicle", 1280, 230, 1920, 886),  # postal van
    ("waymo", 0, "SIDE_LEFT", "vehicle", 0, 520, 330, 886),
    ("waymo", 0, "SIDE_LEFT", "building", 600, 0, 1300, 580),
    ("waymo", 0, "SIDE_LEFT", "sidewalk", 340, 600, 1260, 765),  # the pavement before the shop front
    ("waymo", 0, "SIDE_RIGHT", "vehicle", 500, 450, 1350, 800),  # grey saloon
    ("waymo", 0, "SIDE_RIGHT", "vehicle", 0, 540, 620, 886),
    ("waymo", 0, "SIDE_RIGHT", "building", 620, 0, 1920, 440),
]


# --- sources -------------------------------------------------------------------------------------


def render_worlds(n: int, cfg: DatasetConfig) -> list[dict]:
    """The rig images at T of test samples 0..n-1 with their semantics:
    [{"source": "worlds", "image": "<style> <seed> <camera>", "rgb", "semantic", "fx"}].

    The colour comes from `render_frames`, the package's own rendering of a world's rig (what
    `make_sample` stores, whatever albedo the textures of the day use); the semantics from a
    second, unshaded pass of each camera at the same pose and instant."""
    out = []
    for i in track(range(n), description=f"rendering {n} worlds"):
        world = generate_world(sample_world_config("test", i, cfg))
        frames = render_frames(world, cfg.rig, t_ref=0.0, image_scale=cfg.image_scale)
        static = Tracer(world.static)
        for im in frames.images:
            actors = world.actor_meshes_at(im.timestamp)  # each camera at its own firing time
            tracers = [static] + ([Tracer(TriangleMesh.concatenate(actors))] if actors else [])
            sem = render_camera(tracers, im.intrinsics, im.cam_to_world, shading=False)["semantic"]
            out.append({"source": "worlds", "image": f"{world.config.style} {world.config.seed} {im.name}", "index": i,
                        "rgb": np.asarray(im.image), "semantic": np.asarray(sem), "fx": float(im.intrinsics.fx)})
    return out


def worlds_masks(semantic: np.ndarray) -> dict[str, np.ndarray]:
    masks = {c: np.isin(semantic, [label_id(n) for n in names]) for c, names in WORLDS_CLASSES.items()}
    masks["all"] = semantic != label_id("sky")
    return masks


def load_real(data: Path) -> tuple[list[dict], dict[str, str]]:
    """The real images REGIONS names, with their class rectangles:
    [{"source", "image", "rgb", "fx", "rects": [(class, x0, y0, x1, y1)]}], and {set: why skipped}."""
    wanted: dict[tuple[str, int, str], list] = {}
    for s, idx, cam, cls, *rect in REGIONS:
        wanted.setdefault((s, idx, cam), []).append((cls, *rect))
    images, skipped = [], {}
    for name, (folder, adapter, options) in REAL_SETS.items():
        root = data / folder
        if not root.exists():
            skipped[name] = f"{root} is absent"
            continue
        keys = [k for k in wanted if k[0] == name]
        ds = open_dataset(adapter, root, **options)
        if not keys:
            has_images = len(ds) > 0 and ds[0].frames is not None
            skipped[name] = "no regions marked in REGIONS" if has_images else "no camera images in this set"
            continue
        for idx in sorted({k[1] for k in keys}):
            sample = ds[idx]
            if sample.frames is None:
                skipped[name] = f"sample {idx} has no camera images"
                continue
            for _, _, cam in [k for k in keys if k[1] == idx]:
                im = sample.frames[cam]
                images.append({"source": name, "image": f"{sample.name} {cam}", "rgb": np.asarray(im.image),
                               "fx": float(im.intrinsics.fx), "rects": wanted[(name, idx, cam)]})
    return images, skipped


def real_masks(shape: tuple[int, int], rects: list, scale: float) -> dict[str, np.ndarray]:
    """Class masks at the common scale (`scale` = output / input pixels) from the rectangles;
    "all" is the image without its sky and ignore rectangles."""
    masks = {"all": np.ones(shape, bool)}
    for cls, x0, y0, x1, y1 in rects:
        # the rectangle's pixels after resampling: the output pixels whose area lies inside it
        r0, r1 = math.ceil(y0 * scale), math.floor(y1 * scale)
        c0, c1 = math.ceil(x0 * scale), math.floor(x1 * scale)
        if cls in ("sky", "ignore"):
            masks["all"][r0:r1, c0:c1] = False
            continue
        masks.setdefault(cls, np.zeros(shape, bool))[r0:r1, c0:c1] = True
    return masks


# --- measuring -----------------------------------------------------------------------------------


def measure(images: list[dict]) -> None:
    """Bring each image to the common scale and sample its texture per class, in place: grey,
    scale, masks, samples {class: per-pixel arrays}, stats {class: statistics}."""
    for im in images:
        rgb = to_common_scale(im["rgb"], im["fx"])
        im["grey"] = to_grey(rgb)
        im["common_rgb"] = rgb
        im["scale"] = rgb.shape[0] / im["rgb"].shape[0]
        if "semantic" in im:  # nearest label: the semantics are only resampled where the image is
            rows = np.minimum((np.arange(rgb.shape[0]) + 0.5) / im["scale"], im["rgb"].shape[0] - 1).astype(int)
            cols = np.minimum((np.arange(rgb.shape[1]) + 0.5) / im["scale"], im["rgb"].shape[1] - 1).astype(int)
            im["masks"] = worlds_masks(im["semantic"][np.ix_(rows, cols)])
        else:
            im["masks"] = real_masks(im["grey"].shape, im["rects"], im["scale"])
        im["samples"] = {c: texture_samples(im["grey"], m) for c, m in im["masks"].items()}
        im["stats"] = {c: summarise(s) for c, s in im["samples"].items()}


def pooled(images: list[dict], cls: str) -> dict:
    """The statistics of one class over the pixels of all `images` together."""
    parts = [im["samples"][cls] for im in images if cls in im["samples"]]
    if not parts:
        return summarise(None)
    return summarise({k: np.concatenate([p[k] for p in parts]) for k in parts[0]})


def value_range(images: list[dict], cls: str) -> dict | None:
    """{stat: (min, max)} of the per-image values of `cls` (images with >= MIN_PIXELS), None if none."""
    vals = [im["stats"][cls] for im in images if cls in im["stats"] and im["stats"][cls]["pixels"] >= MIN_PIXELS]
    if not vals:
        return None
    out = {k: (min(v[k] for v in vals), max(v[k] for v in vals)) for k in STATS}
    out["images"] = len(vals)
    return out


def where(value: float, rng: tuple[float, float]) -> str:
    if math.isnan(value):
        return "-"
    return "low" if value < rng[0] else "high" if value > rng[1] else "in"


def tabulate(worlds: list[dict], real: list[dict]) -> tuple[list[dict], dict]:
    """Rows (per class: worlds, worlds range, each real set, real range) and the verdicts
    {class: {stat: in | low | high}} of the pooled worlds value against the real range."""
    rows, verdicts = [], {}
    sets = [s for s in REAL_SETS if any(im["source"] == s for im in real)]
    for cls in CLASSES:
        w = pooled(worlds, cls)
        rr = value_range(real, cls)
        verdicts[cls] = {k: where(w[k], rr[k]) for k in STATS} if rr else {}
        rows.append({"class": cls, "source": "worlds", **w, "images": sum(im["stats"][cls]["pixels"] > 0 for im in worlds),
                     "verdict": verdicts[cls]})
        wr = value_range(worlds, cls)
        if wr:
            rows.append({"class": cls, "source": "worlds range", "range": {k: wr[k] for k in STATS},
                         "images": wr["images"]})
        for s in sets:
            ims = [im for im in real if im["source"] == s and cls in im["samples"]]
            if ims:
                rows.append({"class": cls, "source": s, **pooled(ims, cls), "images": len(ims)})
        if rr:
            rows.append({"class": cls, "source": "real range", "range": {k: rr[k] for k in STATS},
                         "images": rr["images"]})
    return rows, verdicts


# --- output --------------------------------------------------------------------------------------

HEADER = ["class", "source", "grad. energy x1e-3", "contrast 7", "contrast 15", "matchable", "pixels", "images"]
SCALE = {"gradient_energy": 1e3, "contrast_7": 1.0, "contrast_15": 1.0, "matchable": 1.0}


def _cells(row: dict) -> list[str]:
    out = [row["class"], row["source"]]
    for k in STATS:
        if "range" in row:
            lo, hi = row["range"][k]
            out.append(f"{lo * SCALE[k]:.3g}-{hi * SCALE[k]:.3g}")
        else:
            v = row[k] * SCALE[k]
            text = "-" if math.isnan(v) else f"{v:.3g}"
            verdict = row.get("verdict", {}).get(k)
            out.append(text if verdict is None or verdict == "in" else f"{text} {verdict.upper()}")
    out.append(f"{row['pixels']:,}" if "pixels" in row else "")
    out.append(str(row.get("images", "")))
    return out


def markdown(rows: list[dict], notes: list[str]) -> str:
    lines = ["# Texture statistics: worlds against real images", ""]
    for note in notes:
        lines += [note, ""]
    lines += ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    lines += ["| " + " | ".join(_cells(r)) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def console_table(rows: list[dict]) -> str:
    cells = [HEADER] + [_cells(r) for r in rows]
    widths = [max(len(c[i]) for c in cells) for i in range(len(HEADER))]
    lines = []
    for j, c in enumerate(cells):
        if j > 0 and c[0] != cells[j - 1][0] and j > 1:
            lines.append("")
        lines.append("  ".join(x.ljust(w) for x, w in zip(c, widths)))
    return "\n".join(lines)


def _best_crop(mask: np.ndarray, size: int) -> tuple[float, int, int]:
    """(coverage, row, col) of the size x size crop that the mask covers most (top-left corner)."""
    h, w = mask.shape
    if h < size or w < size:
        return 0.0, 0, 0
    cover = ndimage.uniform_filter(mask.astype(np.float64), size=size, mode="constant")
    half = size // 2
    inner = cover[half:h - size + half + 1, half:w - size + half + 1]  # crops wholly inside the image
    r, c = np.unravel_index(np.argmax(inner), inner.shape)
    return float(inner[r, c]), int(r), int(c)


def crops(worlds: list[dict], real: list[dict], cls: str, n_worlds: int = 3, n_real: int = 4) -> list[dict]:
    """Crops of `cls` at the common scale: the worlds images' best-covered crops (one per world)
    and the real rectangles' centres (one per real set first), each up to CROP x CROP."""
    out = []
    cands = []
    for im in worlds:
        if cls in im["masks"]:
            cov, r, c = _best_crop(im["masks"][cls], CROP)
            cands.append((cov, im, r, c))
    seen = set()
    for cov, im, r, c in sorted(cands, key=lambda t: -t[0]):
        world = " ".join(im["image"].split()[:2])
        if cov < 0.6 or world in seen:
            continue
        seen.add(world)
        style, _, camera = im["image"].split()
        out.append({"title": f"worlds {style} #{im['index']}\n{camera}", "rgb": im["common_rgb"][r:r + CROP, c:c + CROP],
                    "c7": im["stats"][cls]["contrast_7"]})
        if len(out) == n_worlds:
            break
    # per real set its largest rectangle of the class (the most texture to show), largest first
    largest: dict[str, tuple] = {}
    for im in real:
        for rect in im["rects"]:
            _, x0, y0, x1, y1 = rect
            area = (x1 - x0) * (y1 - y0) * im["scale"] ** 2
            if rect[0] == cls and area > largest.get(im["source"], (0.0,))[0]:
                largest[im["source"]] = (area, im, rect)
    order = [(im, rect) for _, im, rect in sorted(largest.values(), key=lambda t: -t[0])]
    for im, (_, x0, y0, x1, y1) in order[:n_real]:
        s = im["scale"]
        r0, r1, c0, c1 = math.ceil(y0 * s), math.floor(y1 * s), math.ceil(x0 * s), math.floor(x1 * s)
        rc, cc = (r0 + r1) // 2, (c0 + c1) // 2
        hr, hc = min(CROP, r1 - r0) // 2, min(CROP, c1 - c0) // 2
        out.append({"title": f"{im['source']}\n{im['image'].split()[-1]}",
                    "rgb": im["common_rgb"][rc - hr:rc + hr, cc - hc:cc + hc], "c7": im["stats"][cls]["contrast_7"]})
    return out


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    return plt


def figure(worlds: list[dict], real: list[dict], path: Path, label: str) -> None:
    plt = _pyplot()
    rows = [(cls, crops(worlds, real, cls)) for cls in FIGURE_CLASSES]
    ncols = max(len(c) for _, c in rows)
    fig, axes = plt.subplots(len(rows), ncols, figsize=(2.0 * ncols, 2.5 * len(rows)), squeeze=False)
    for i, (cls, items) in enumerate(rows):
        for j in range(ncols):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            if j >= len(items):
                ax.axis("off")
                continue
            it = items[j]
            canvas = np.ones((CROP, CROP, 3), np.float32)  # every crop at the same pixel scale
            h, w = it["rgb"].shape[:2]
            canvas[:h, :w] = it["rgb"]
            ax.imshow(canvas, interpolation="nearest")
            ax.set_title(f"{it['title']}  (C7 {it['c7']:.3f})", fontsize=7)
            color = "tab:orange" if it["title"].startswith("worlds") else "tab:blue"
            for sp in ax.spines.values():
                sp.set_edgecolor(color)
                sp.set_linewidth(2)
            if j == 0:
                ax.set_ylabel(cls, fontsize=10)
    fig.suptitle(f"Crops at the common scale (focal {COMMON_FOCAL_PX:g} px, {CROP} px square): worlds (orange) "
                 f"against real (blue), per class{f' [{label}]' if label else ''}\nC7: the whole image's median 7x7 "
                 f"contrast of that class; white: the region is smaller than the crop", fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def draw_regions(real: list[dict], folder: Path) -> None:
    """Each real image with its rectangles drawn and named (to check the REGIONS table)."""
    plt = _pyplot()
    folder.mkdir(parents=True, exist_ok=True)
    for im in real:
        h, w = im["rgb"].shape[:2]
        fig = plt.figure(figsize=(12, 12 * h / w))
        ax = fig.add_axes((0, 0, 1, 1))
        ax.imshow(im["rgb"])
        for cls, x0, y0, x1, y1 in im["rects"]:
            ax.add_patch(plt.Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, color="yellow", lw=1.5))
            ax.text(x0 + 4, y0 + 4, cls, color="yellow", fontsize=9, va="top",
                    bbox={"facecolor": "black", "alpha": 0.5, "pad": 1})
        ax.axis("off")
        fig.savefig(folder / f"{im['source']}_{im['image'].replace(' ', '_')}.png", dpi=100)
        plt.close(fig)


def _no_nan(obj):
    """`obj` with NaN floats as None (null): strict JSON has no NaN."""
    if isinstance(obj, float):
        return None if math.isnan(obj) else obj
    if isinstance(obj, dict):
        return {k: _no_nan(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_no_nan(v) for v in obj]
    return obj


def _write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", type=int, default=8, help="test-split worlds to render (they cycle through the "
                    "styles: 8 = 2 per style; ~2 s each)")
    ap.add_argument("--data", type=Path, default=DATA, help="the real data sets' folder (../shared/data)")
    ap.add_argument("--label", default="", help="written into the output names (texture_statistics_<label>.md, "
                    "texture_crops_<label>.png), to keep runs before and after a texture change side by side")
    ap.add_argument("--before", dest="label", action="store_const", const="before", help="same as --label before")
    ap.add_argument("--after", dest="label", action="store_const", const="after", help="same as --label after")
    ap.add_argument("--out-json", type=Path, default=None, help="the JSON results (the .md is written beside it); "
                    "default experiments/results/texture_statistics[_<label>].json")
    ap.add_argument("--png", type=Path, default=None, help="the crops figure; default docs/texture_crops[_<label>].png")
    ap.add_argument("--draw-regions", type=Path, default=None, help="write the real images with their rectangles here")
    args = ap.parse_args(argv)
    suffix = f"_{args.label}" if args.label else ""
    out_json = args.out_json or REPO / "experiments" / "results" / f"texture_statistics{suffix}.json"
    png = args.png or REPO / "docs" / f"texture_crops{suffix}.png"

    t0 = time.perf_counter()
    # which textures the worlds were rendered with: the file as it was when it was imported (another
    # session may edit it while this runs)
    textures_file = Path(inspect.getsourcefile(albedo))
    textures_sha = hashlib.sha256(textures_file.read_bytes()).hexdigest()
    texture_version = getattr(inspect.getmodule(albedo), "TEXTURE_VERSION", 1)  # 1: before it was numbered
    cfg = DatasetConfig()
    worlds = render_worlds(args.worlds, cfg)
    real, skipped = load_real(args.data)
    for name, why in skipped.items():
        print(f"skipped {name}: {why}")
    measure(worlds)
    measure(real)
    if args.draw_regions:
        draw_regions(real, args.draw_regions)
    rows, verdicts = tabulate(worlds, real)
    notes = [
        (f"Label: {args.label or '(none)'}. Worlds: test samples 0..{args.worlds - 1} ({cfg.rig} at image scale "
         f"{cfg.image_scale}), texture version {texture_version} (textures file sha256 {textures_sha[:12]}). Real: the rectangles of "
         f"experiments/texture_statistics.py REGIONS; skipped: "
         f"{'; '.join(f'{k} ({v})' for k, v in skipped.items()) or 'none'}."),
        (f"Common scale: focal {COMMON_FOCAL_PX:g} px (area-averaged; within 5 % left as is). Statistics over the "
         f"pixels whose 15x15 window lies inside the image and the class region. Grad. energy: mean |grad I|^2 "
         f"(Sobel/8, grey 0-1) x1e-3; contrast: median local std/mean; matchable: share of 7x7 windows with "
         f"std/mean > {MATCHABLE_THRESHOLD:g}. Rows pool a source's pixels; a range is min-max over its images "
         f"(>= {MIN_PIXELS} px); LOW/HIGH: the worlds value outside the real range."),
    ]
    out_json.parent.mkdir(parents=True, exist_ok=True)
    result = {
        "label": args.label, "worlds": args.worlds, "rig": cfg.rig, "image_scale": cfg.image_scale,
        "textures_file": str(textures_file.relative_to(REPO)) if textures_file.is_relative_to(REPO) else str(textures_file),
        "textures_sha256": textures_sha, "texture_version": texture_version, "common_focal_px": COMMON_FOCAL_PX,
        "matchable_threshold": MATCHABLE_THRESHOLD, "min_pixels": MIN_PIXELS, "skipped": skipped,
        "rows": rows, "verdicts": verdicts,
        "per_image": [{"source": im["source"], "image": im["image"], "fx": im["fx"], "scale": im["scale"],
                       "stats": im["stats"]} for im in worlds + real],
        "regions": [list(r) for r in REGIONS],
        "seconds": round(time.perf_counter() - t0, 1),
    }
    _write_text(out_json, json.dumps(_no_nan(result), indent=1, default=float))
    md = out_json.with_suffix(".md")
    _write_text(md, markdown(rows, notes))
    figure(worlds, real, png, args.label)
    print(console_table(rows))
    print(f"\nwrote {out_json}, {md}, {png} ({result['seconds']} s)")


if __name__ == "__main__":
    main()
