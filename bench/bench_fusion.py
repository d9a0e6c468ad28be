"""The evidence route after stereo on the compiled core against the NumPy walk (issue 44's cost).

The fusion carves free space along every confident pixel's ray (`model/geometry/fusion.py`,
`_misses`): the walk runs in the compiled trace core (`compiled.carve_misses`) or in NumPy, to the
same bytes. This fuses the depth maps of worlds test sample 0 (made on the fly, as `worlds
generate` makes it) at the `evidence` profile's references (T, T-3 and T+3: 15 maps of the five
cameras) with each, in the same process, interleaved: seconds (best
of `--repeats`) for the fusion alone and for everything after stereo (fusion, ground height field,
surfels: `fuse_evidence` and `scene_from_evidence`), the ratio, and whether the two give the same
arrays. The depth is the renderer's (exact, confidence 1): stereo leaves a fifth to a half of the
pixels unsure, so the route's own fusion walks fewer rays than this. No dataset needed.
Run: `python -m bench.bench_fusion [--repeats 2]`. Results: bench/results/fusion.{json,md}.
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from scube_sim.raytrace import compiled

from .common import best_per_core, write_results

PROFILE = "evidence"


def _observations(profile):
    """Worlds test sample 0 as the converter's data has it (waymo-5 at 0.25 scale), its depth maps
    at the profile's references (exact depth, confidence 1, chunk frame), the chunk's corner and
    world -> chunk."""
    from scube_sim.camera.frames import chunk_to_world
    from scube_sim.reconstruct.evidence import grid_corner
    from scube_sim.reconstruct.fusion import DepthObservation
    from scube_sim.transforms import invert_pose
    from scube_sim.worlds.dataset import DatasetConfig, make_sample, sample_frames

    offsets = sorted(profile.evidence.references)
    sample = make_sample("test", 0, DatasetConfig(frame_offsets=offsets))
    at = {f["offset"]: i for i, f in enumerate(sample["meta"]["frames"])}
    to_chunk = invert_pose(chunk_to_world(sample_frames(sample)))
    obs = []
    for offset in profile.evidence.references:
        for im in sample_frames(sample, at[offset]).images:
            depth = np.where(np.isfinite(im.depth), im.depth, np.nan).astype(np.float32)
            moved = dataclasses.replace(im, cam_to_world=to_chunk @ im.cam_to_world)
            obs.append(DepthObservation(moved, depth, np.isfinite(depth).astype(np.float32)))
    return obs, grid_corner(sample_frames(sample), to_chunk), to_chunk


def _arrays(x) -> list[np.ndarray]:
    """A VoxSplat's arrays (geometry, parameters, labels, channels), or a fused grid's."""
    if hasattr(x, "params"):
        return [x.ijk, x.params, x.valid, x.labels, *[c.data for c in x.channels.values()]]
    return [v for v in vars(x).values() if isinstance(v, np.ndarray)]


def _same(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(_arrays(a), _arrays(b), strict=True))


def run(repeats: int = 2) -> list[dict]:
    from scube_sim.converter.profile import load_profile
    from scube_sim.reconstruct.evidence import fuse_evidence
    from scube_sim.reconstruct.fusion import fuse_depth
    from scube_sim.reconstruct.surfels import scene_from_evidence

    if not compiled.available():
        raise SystemExit(f"the compiled core is not built: {compiled.load_error()}")
    profile = load_profile(PROFILE)
    cfg = profile.evidence
    obs, corner, to_chunk = _observations(profile)
    stages = {
        "fusion (fuse_depth)": lambda: fuse_depth(obs, cfg.fusion_at_stereo_scale(), origin=corner),
        "after stereo (fusion, ground, surfels)": lambda: scene_from_evidence(fuse_evidence(obs, corner, to_chunk,
                                                                                            cfg), cfg),
    }
    rows = []
    for stage, fn in stages.items():
        sec, out = best_per_core(fn, repeats)
        rows.append({"stage": stage, "depth_maps": len(obs), "numpy_s": round(sec["reference"], 2),
                     "compiled_s": round(sec["compiled"], 2), "speedup": round(sec["reference"] / sec["compiled"], 2),
                     "same_output": _same(out["reference"], out["compiled"])})
        print(rows[-1])
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    rows = run(args.repeats)
    write_results("fusion", rows, list(rows[0]),
                  notes="worlds test sample 0's depth maps (renderer's depth, confidence 1) at the evidence profile's "
                        "references T, T-3, T+3 (15 maps, waymo-5 at the converter's image scale), fused with the "
                        "carving walk in NumPy and on the compiled core, interleaved, best of "
                        f"{args.repeats}; same_output: every array equal")


if __name__ == "__main__":
    main()
