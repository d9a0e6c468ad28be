"""Moving boxed objects between the instants of a log: which objects moved (`moved_boxes`), which
pixels of an image see one (`moved_pixels`), and each mover's box at every instant (`mover_tracks`),
for `mvs` step 4b. Boxes and poses in the world frame, metres; pixels in the image's own grid.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
import torch.nn.functional as F

from ...boxes import Box
from ...camera.frames import CameraImage
from ..config import StereoConfig

__all__ = ["box_mask", "crop", "moved_boxes", "moved_pixels", "mover_tracks"]


def _key(b: Box):
    return ("instance", int(b.instance)) if b.instance else (("track", b.track_id) if b.track_id else None)


def _displaced(a: Box, b: Box, moved_m: float) -> bool:
    """Whether one object's boxes at two instants differ: centre over `moved_m`, or turned over about a degree."""
    return bool(np.linalg.norm(b.center - a.center) > moved_m or np.abs(b.rotation - a.rotation).max() > 0.02)


def _moved(ref_boxes: list[Box], src_boxes: list[Box], moved_m: float) -> tuple[list[Box], list[Box]]:
    """The boxes, at the reference instant and at the source's, of the objects that moved between
    them (centre moved over `moved_m`, or turned over about a degree); a box without an identity or
    without a match at the other instant counts as moved (nothing says it stood still)."""
    src_by = {_key(b): b for b in src_boxes if _key(b) is not None}
    ref_by = {_key(b): b for b in ref_boxes if _key(b) is not None}
    moved_ref, moved_src = [], []
    for b in ref_boxes:
        o = src_by.get(_key(b)) if _key(b) is not None else None
        if o is None or _displaced(b, o, moved_m):
            moved_ref.append(b)
            if o is not None:
                moved_src.append(o)
    moved_src += [b for b in src_boxes if _key(b) is None or _key(b) not in ref_by]
    return moved_ref, moved_src


def box_mask(boxes: list[Box], cam_to_world: np.ndarray, k: np.ndarray, hw: tuple[int, int], margin_m: float,
              dilate_px: int) -> torch.Tensor | None:
    """(h, w) bool: the pixels of a pinhole camera (K, pose) whose ray meets one of `boxes` (each
    grown by `margin_m`) in front of the camera (a slab test), dilated by `dilate_px`; None if none.
    A box wholly in front of the camera is tested only on the pixels around its corners'
    projection (a convex box's image lies within it); others on every pixel."""
    if not boxes:
        return None
    h, w = hw
    r_cam, c_cam = cam_to_world[:3, :3], cam_to_world[:3, 3]
    mask = np.zeros((h, w), bool)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
    for b in boxes:
        half = b.size / 2 + margin_m
        rows, cols = slice(0, h), slice(0, w)
        corners = ((b.center + (signs * half) @ b.rotation.T) - c_cam) @ r_cam  # camera frame
        if np.all(corners[:, 2] > 1e-6):
            u = k[0, 0] * corners[:, 0] / corners[:, 2] + k[0, 2] - 0.5  # continuous pixel index
            v = k[1, 1] * corners[:, 1] / corners[:, 2] + k[1, 2] - 0.5
            # two pixels of slack: the slab test's rounding at the silhouette stays inside
            c0, c1 = max(int(np.floor(u.min())) - 2, 0), min(int(np.ceil(u.max())) + 3, w)
            r0, r1 = max(int(np.floor(v.min())) - 2, 0), min(int(np.ceil(v.max())) + 3, h)
            if c0 >= c1 or r0 >= r1:
                continue  # in front of the camera but outside its image
            rows, cols = slice(r0, r1), slice(c0, c1)
        vv, uu = np.meshgrid(np.arange(rows.start, rows.stop) + 0.5, np.arange(cols.start, cols.stop) + 0.5,
                             indexing="ij")
        rays = np.stack([(uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1], np.ones_like(uu)], -1).reshape(-1, 3)
        o = b.rotation.T @ (c_cam - b.center)  # camera centre in the box frame
        d = (rays @ r_cam.T) @ b.rotation  # ray directions in the box frame
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half - o) / d, (half - o) / d
        t1 = np.where(np.abs(d) < 1e-12, np.where(np.abs(o) <= half, -np.inf, np.inf), t1)
        t2 = np.where(np.abs(d) < 1e-12, np.where(np.abs(o) <= half, np.inf, -np.inf), t2)
        lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
        # the three slabs' entry and exit, column by column (the same values as .max(1) / .min(1), faster)
        tmin = np.maximum(np.maximum(lo[:, 0], lo[:, 1]), lo[:, 2])
        tmax = np.minimum(np.minimum(hi[:, 0], hi[:, 1]), hi[:, 2])
        hit = (tmax >= np.maximum(tmin, 0.0)) & (tmax > 0)
        mask[rows, cols] |= hit.reshape(rows.stop - rows.start, cols.stop - cols.start)
    out = torch.from_numpy(mask)
    if dilate_px > 0:
        out = F.max_pool2d(out[None, None].to(torch.float32), 2 * dilate_px + 1, stride=1, padding=dilate_px)[0, 0] > 0
    return out if bool(out.any()) else None


def moved_boxes(here: list[Box], there: list[Box], cfg: StereoConfig | None = None) -> tuple[list[Box], list[Box]]:
    """The boxes, at the instant of `here` and at that of `there`, of the objects that moved between
    the two (`_moved`'s rule with `cfg.moved_m`)."""
    return _moved(here, there, (cfg or StereoConfig()).moved_m)


def moved_pixels(im: CameraImage, here: list[Box], there: list[Box], cfg: StereoConfig | None = None) -> np.ndarray:
    """(H, W) bool: the pixels of `im` (at the instant of boxes `here`) that see an object whose box
    moved by another instant (boxes `there`; `_moved`'s rule, grown by `box_margin_m`): a depth
    measured there belongs to that instant only. Distortion is ignored (the box margin covers it)."""
    cfg = cfg or StereoConfig()
    intr = im.intrinsics
    moved, _ = _moved(here, there, cfg.moved_m)
    mask = box_mask(moved, np.asarray(im.cam_to_world, np.float64), intr.K, (intr.height, intr.width),
                     cfg.box_margin_m, 0)
    return np.zeros((intr.height, intr.width), bool) if mask is None else mask.numpy()


def mover_tracks(boxes: dict, cfg: StereoConfig) -> list[dict[int, Box]]:
    """Per object boxed at the reference instant (offset 0) that moved by another instant
    (`_moved`'s rule), its box at every instant that has one (offset -> Box)."""
    out = []
    for b in boxes.get(0, []):
        key = _key(b)
        if key is None:
            continue
        at = {0: b}
        for offset, there in boxes.items():
            match = next((o for o in there if _key(o) == key), None) if offset != 0 else None
            if match is not None:
                at[offset] = match
        if any(_displaced(b, o, cfg.moved_m) for o in at.values()):
            out.append(at)
    return out


def crop(im: CameraImage, rows: slice, cols: slice) -> CameraImage:
    """The part of `im` in `rows` x `cols` (original pixels): a camera with its principal point moved."""
    intr = im.intrinsics
    part = dataclasses.replace(intr, width=cols.stop - cols.start, height=rows.stop - rows.start,
                               cx=intr.cx - cols.start, cy=intr.cy - rows.start)
    return CameraImage(im.name, np.ascontiguousarray(im.image[rows, cols]), part, im.cam_to_world, im.timestamp)
