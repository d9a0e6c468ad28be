"""Source-view selection for plane-sweep stereo: which other images see the reference's surfaces
with a parallax the sweep's hypotheses can resolve.

Candidates: the other cameras at the reference instant and every camera at the context instants
(`candidates`). Each is scored on a coarse grid of the reference's pixel rays (`GRID` x `GRID`)
at a few working depths (`WORKING_DEPTHS_M`): a grid point counts where it lands inside the
candidate's image and in front of it, weighted by how far it moves in the candidate between two
neighbouring depth hypotheses (``step_px``: the sweep samples the cost curve at that spacing).
The weight is min(s, 1 / s) with s = step_px / `GOOD_STEP_PX`: 1 at one pixel per hypothesis, less
for a short baseline (little parallax over the whole depth range: a flat cost curve) and for a
long one (the curve undersampled between hypotheses: the minimum is missed). Refused outright:
a camera-centre distance under `min_baseline_m` (a stopped ego gives no baseline), optical axes
more than `max_axis_angle_deg` apart (a huge change of viewpoint), a share of grid points landing
inside under `MIN_OVERLAP`, and fisheye cameras (the sweep is pinhole only).

Frames: OpenCV cameras; `cam_to_world` (4, 4) poses; ref_to_src = inv(src.cam_to_world) @
ref.cam_to_world (reference-camera coordinates -> source-camera coordinates). Lens distortion is
left out of the scoring (the grid is coarse: pinhole rays of each camera's K).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...camera.frames import CameraImage, Frames
from ...transforms import invert_pose

GRID = 16  # reference rays per side of the scoring grid
WORKING_DEPTHS_M = (4.0, 10.0, 25.0, 60.0)
GOOD_STEP_PX = 1.0  # pixels of motion per hypothesis step the score prefers
MIN_OVERLAP = 0.2  # share of the grid points (all depths) that must land inside a source
MIN_BASELINE_M = 0.05
MAX_AXIS_ANGLE_DEG = 60.0

__all__ = ["GOOD_STEP_PX", "GRID", "MAX_AXIS_ANGLE_DEG", "MIN_BASELINE_M", "MIN_OVERLAP", "WORKING_DEPTHS_M",
           "SourceView", "candidates", "score_view", "select_sources"]


@dataclass(frozen=True)
class SourceView:
    """A chosen source: its image, its instant's `offset` (0: the reference instant), ref_to_src
    (4, 4) reference-camera -> source-camera, `score` (in [0, 1], higher is better), `overlap`
    (share of grid points landing inside it) and `baseline_m` (camera-centre distance, metres)."""

    image: CameraImage
    offset: int
    ref_to_src: np.ndarray
    score: float
    overlap: float
    baseline_m: float


def candidates(frames: Frames, index: int) -> list[tuple[int, CameraImage]]:
    """(offset, image) of every image of `frames` but the reference `index`: the other cameras at
    the reference instant (offset 0) and every camera of each context instant."""
    out = [(0, im) for k, im in enumerate(frames.images) if k != index]
    for c in frames.context:
        out += [(c.offset, im) for im in c.images]
    return out


def _grid_rays(im: CameraImage) -> np.ndarray:
    """(GRID * GRID, 3) float64 pinhole rays (z = 1) through a regular grid of the image, camera frame."""
    intr = im.intrinsics
    u = (np.arange(GRID) + 0.5) * intr.width / GRID
    v = (np.arange(GRID) + 0.5) * intr.height / GRID
    uu, vv = np.meshgrid(u, v)
    return np.stack([(uu.ravel() - intr.cx) / intr.fx, (vv.ravel() - intr.cy) / intr.fy, np.ones(uu.size)], 1)


def _project(k: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) camera points -> (N, 2) pixels (pinhole K) and (N,) z."""
    z = p[:, 2]
    zs = np.where(z > 1e-6, z, 1.0)
    return (p @ k.T)[:, :2] / zs[:, None], z


def score_view(ref: CameraImage, src: CameraImage, inv_depth_step: float, *, min_baseline_m: float = MIN_BASELINE_M,
               max_axis_angle_deg: float = MAX_AXIS_ANGLE_DEG,
               good_step_px: float = GOOD_STEP_PX) -> tuple[float, float, float, np.ndarray]:
    """(score, overlap, baseline_m, ref_to_src) of `src` as a source for `ref` (module docstring);
    `inv_depth_step` (1/m) is the sweep's step between neighbouring hypotheses, `good_step_px` the
    motion per step preferred, in the source image's pixels. Score 0 where refused."""
    ref_to_src = invert_pose(src.cam_to_world) @ ref.cam_to_world
    baseline = float(np.linalg.norm(ref_to_src[:3, 3]))
    axis_cos = float(ref.cam_to_world[:3, 2] @ src.cam_to_world[:3, 2])
    if (src.intrinsics.model == "fisheye" or baseline < min_baseline_m
            or axis_cos < np.cos(np.deg2rad(max_axis_angle_deg))):
        return 0.0, 0.0, baseline, ref_to_src
    rays = _grid_rays(ref)
    rot, t = ref_to_src[:3, :3], ref_to_src[:3, 3]
    k = src.intrinsics.K
    w, h = src.intrinsics.width, src.intrinsics.height
    inside_all, weights = [], []
    for d in WORKING_DEPTHS_M:
        uv, z = _project(k, (d * rays) @ rot.T + t)
        d2 = 1.0 / (1.0 / d + inv_depth_step)  # the next hypothesis nearer the far end
        uv2, z2 = _project(k, (d2 * rays) @ rot.T + t)
        inside = (z > 1e-6) & (z2 > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] <= w) & (uv[:, 1] >= 0) & (uv[:, 1] <= h)
        s = np.linalg.norm(uv2 - uv, axis=1) / good_step_px
        weights.append(np.where(inside, np.minimum(s, 1.0 / np.maximum(s, 1e-12)), 0.0))
        inside_all.append(inside)
    overlap = float(np.mean(inside_all))
    if overlap < MIN_OVERLAP:
        return 0.0, overlap, baseline, ref_to_src
    return float(np.mean(weights)), overlap, baseline, ref_to_src


def select_sources(ref: CameraImage, cands: list[tuple[int, CameraImage]], count: int, inv_depth_step: float, *,
                   min_baseline_m: float = MIN_BASELINE_M,
                   max_axis_angle_deg: float = MAX_AXIS_ANGLE_DEG, good_step_px: float = GOOD_STEP_PX) -> list[SourceView]:
    """The best `count` of `cands` ((offset, image) pairs, `candidates`) for `ref`, best first; only
    those with a positive score. Ties: the smaller |offset|, then the offset, then the camera name
    (deterministic). Scores are rounded to 1e-9 so float noise does not reorder equal views."""
    scored = []
    for offset, im in cands:
        score, overlap, baseline, ref_to_src = score_view(ref, im, inv_depth_step, min_baseline_m=min_baseline_m,
                                                          max_axis_angle_deg=max_axis_angle_deg,
                                                          good_step_px=good_step_px)
        if score > 0:
            scored.append(SourceView(im, int(offset), ref_to_src, round(score, 9), overlap, baseline))
    scored.sort(key=lambda s: (-s.score, abs(s.offset), s.offset, s.image.name))
    return scored[: max(0, int(count))]
