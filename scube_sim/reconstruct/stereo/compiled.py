"""The compiled plane sweep (`_sweep.cpp`): `mvs._volume`'s census cost volume in C++, threaded
over hypotheses, the same bytes for any thread count; the semi-global aggregation of that volume
(`semi_global`, threaded over the paths' lines) and its winner-take-all (`winner_take_all`).
`mvs._volume`, `sgm.semi_global` and `winner.winner_take_all` run them wherever the extension was
built; `mvs._volume_reference`, `sgm.semi_global_reference` and `winner.winner_take_all_reference`
(torch) are what they are tested against.

It repeats the reference's arithmetic step by step (`_sweep.cpp` lists them): the warp's float64
homography and float32 grid, grid_sample's bilinear and nearest sampling (align_corners=False,
border padding) with the fused multiply-adds of torch's vectorised CPU kernel, the census of the
warped grey against the reference's, the window box as a row then a column pass, the robust mean
over sources. Where torch runs another kernel (a CPU without FMA) a sample may differ in its last
bit, and with it, rarely, a census bit.

`available()` tells whether the extension imports; `load_error()` why not. The core follows the
tracer's `SCUBE_SIM_CORE` (`raytrace.compiled.CORE_ENV`): 'reference' runs the torch path,
'compiled' requires the extension, 'auto' (default) takes it where built and says once, where it
is not, that stereo runs on the torch path.
"""

from __future__ import annotations

import numpy as np
import torch
from rich.progress import track

from ...cpus import resolve_threads
from ...raytrace.compiled import CoreUnavailable, choose_core
from .sweep import CONF_EPS, MIN_SOURCE_Z, grey, plane_terms

try:
    from . import _sweep
    _LOAD_ERROR: str | None = None
except ImportError as exc:  # the extension was not built on this install
    _sweep = None
    _LOAD_ERROR = f"{type(exc).__name__}: {exc}"

__all__ = ["available", "default_core_name", "load_error", "semi_global", "volume", "winner_take_all"]

def available() -> bool:
    return _sweep is not None


def load_error() -> str | None:
    """Why the compiled sweep does not import (None when it does)."""
    return _LOAD_ERROR


def default_core_name() -> str:
    """'compiled' or 'reference': the stereo sweep `mvs._volume` runs (`raytrace.compiled.choose_core`)."""
    return choose_core("stereo sweep", available(), _LOAD_ERROR,
                       "stereo runs on the torch reference path, many times slower. Install a C++ compiler, then "
                       "reinstall the package.")


def _numpy(x, dtype) -> np.ndarray:
    x = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    return np.ascontiguousarray(x, dtype=dtype)


def volume(ref_img, k_ref, ref_ok, hw, srcs, views, hyps, cfg, bar: str | None, *, threads: int = 0,
           portable: bool = False):
    """`mvs._volume` in the compiled sweep: the aggregated census cost volume and per source its
    own curve's minimum, the hypothesis of it and its maximum.

    ref_img (C, h, w) float32 (the reference on its pinhole grid, intensities in [0, 1]); k_ref
    (3, 3) its K; ref_ok (h, w) bool (the pixel's ray lands in the original image); hw (h, w);
    srcs: per source (image (C, Hs, Ws) float32, K (3, 3), reference-side mask (h, w) bool or None
    (True: not matched there), source-side mask (1, Hs, Ws) float32 or None (>= 0.5: masked));
    views: the `SourceView`s (`ref_to_src` (4, 4) reference camera -> source camera); hyps (D,)
    depths in metres along the reference camera's z; cfg: `StereoConfig` (`window`; `chunk`, the
    hypotheses per progress step at the least); bar: a progress description (None: no bar);
    threads: 0 resolves with `cpus.resolve_threads`; portable: the extension's portable build even
    where its AVX2 / FMA one runs (the same values; for tests).

    Returns the volume (D, h, w) float32 (NaN where no source sees the entry), and per source
    best (h, w) float32 (inf where it sees nothing), arg (h, w) int64 (the first hypothesis at the
    minimum, 0 where none) and worst (h, w) float32 (-inf where none)."""
    if _sweep is None:
        raise CoreUnavailable(f"the compiled stereo sweep is not built ({_LOAD_ERROR})")
    threads = resolve_threads(threads)
    h, w = (int(s) for s in hw)
    imgs, a_terms, b_terms, ref_masks, src_masks = [], [], [], [], []
    for (img, k_src, ref_mask, src_mask), view in zip(srcs, views, strict=True):
        a, b = plane_terms(k_src, k_ref, view.ref_to_src, (h, w))
        imgs.append(_numpy(img, np.float32))
        a_terms.append(_numpy(a, np.float64))
        b_terms.append(_numpy(b.reshape(-1), np.float64))
        ref_masks.append(None if ref_mask is None else _numpy(ref_mask, np.bool_).view(np.uint8))
        src_masks.append(None if src_mask is None else _numpy(src_mask[0], np.float32))
    ref_grey = _numpy(grey(torch.as_tensor(ref_img)), np.float32)
    sweep = _sweep.CensusSweep(ref_grey, _numpy(ref_ok, np.bool_).view(np.uint8), imgs, a_terms, b_terms,
                               ref_masks, src_masks, int(cfg.window), float(MIN_SOURCE_Z), bool(portable))
    depths = _numpy(torch.as_tensor(hyps, dtype=torch.float64).reshape(-1), np.float64)
    n_src = len(imgs)
    agg = np.empty((len(depths), h, w), np.float32)
    best = np.full((n_src, h, w), np.inf, np.float32)
    arg = np.zeros((n_src, h, w), np.int64)
    worst = np.full((n_src, h, w), -np.inf, np.float32)
    # blocks of whole multiples of the thread count (each thread one hypothesis at a time), at least
    # `chunk` hypotheses: the bar's steps, and the memory of one block's per-source planes
    block = -(-max(int(cfg.chunk), threads) // threads) * threads
    starts = list(range(0, len(depths), block))
    for s in (track(starts, description=bar, transient=True) if bar else starts):
        sweep.run(depths[s:s + block], s, agg[s:s + block], best, arg, worst, threads)
    return (torch.from_numpy(agg), [torch.from_numpy(b) for b in best], [torch.from_numpy(a) for a in arg],
            [torch.from_numpy(x) for x in worst])


def semi_global(cost: torch.Tensor, p1: float, p2: float, *, paths: int = 4, fill: float = 0.5, threads: int = 0,
                portable: bool = False) -> torch.Tensor:
    """`sgm.semi_global` in the compiled sweep: cost (D, H, W) float32 (the census share of bits; NaN:
    unseen) -> (D, H, W) float32, the mean of the path costs over `paths` (4 or 8) directions with
    penalties p1, p2 (cost units, taken as float32 as torch takes them), unseen entries entering
    as `fill` and coming back NaN. threads: 0 resolves with `cpus.resolve_threads`; portable: as
    `volume`'s."""
    if _sweep is None:
        raise CoreUnavailable(f"the compiled stereo sweep is not built ({_LOAD_ERROR})")
    out = _sweep.semi_global(_numpy(cost, np.float32), float(p1), float(p2), int(paths), float(fill),
                             resolve_threads(threads), bool(portable))
    return torch.from_numpy(out)


def winner_take_all(cost: torch.Tensor, depths, *, threads: int = 0, portable: bool = False):
    """`winner.winner_take_all` in the compiled sweep: cost (D, H, W) float32 (NaN: no candidate),
    depths (D,) metres -> depth (H, W) float32 metres, best cost (H, W) float32, confidence (H, W)
    float32 in [0, 1], and the winning hypothesis (H, W) int64. threads, portable: as `volume`'s."""
    if _sweep is None:
        raise CoreUnavailable(f"the compiled stereo sweep is not built ({_LOAD_ERROR})")
    inv = 1.0 / torch.as_tensor(depths, dtype=torch.float64).reshape(-1)  # as the reference computes it
    out = _sweep.winner_take_all(_numpy(cost, np.float32), _numpy(inv, np.float64), float(CONF_EPS),
                                 resolve_threads(threads), bool(portable))
    return tuple(torch.from_numpy(x) for x in out)
