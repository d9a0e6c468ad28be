"""Stereo benchmark: the compiled plane sweep (`reconstruct/stereo/_sweep.cpp`) against the torch
reference (`mvs._volume_reference`), in one process on the same inputs (issue 72).

- Frames: the demo's world and rig (`runs.demo`: the urban x-junction, waymo-5 at the converter's
  image scale, +-4 context instants at 10 Hz), rendered on the fly.
- Settings: the `evidence` profile's stereo (`StereoConfig` with its overrides; moving objects
  swept again in their own frames at T, as `measure_evidence` does).
- Per reference image (the five cameras at T): the sweep alone (`_volume`: warps, census costs,
  robust mean, each source's extremes) with each core, and `stereo_depth` end to end with each
  (`SCUBE_SIM_CORE`: on the compiled core the semi-global aggregation and the winner-take-all run
  compiled too), interleaved so that load drifts hit both alike, best of `--repeats`; the
  ratio; whether the two volumes are the same bytes (and the share of entries that differ), and
  the share of pixels whose depth and confidence agree.
- Threads: both cores use the same count (`cpus.resolve_threads`, torch's intra-op threads set to
  it for the run).

Run: `python -m bench.bench_stereo [--repeats 2] [--quick]` (--quick: two cameras, one repeat).
Results: bench/results/stereo.{json,md}.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from .common import write_results

PROFILE = "evidence"


def _frames():
    from scube_sim.converter.profile import load_profile
    from scube_sim.runs.demo import DEFAULT_WORLD, FRAMES_SCALE
    from scube_sim.worlds.dataset import render_frames_with_context
    from scube_sim.worlds.generator import generate_world

    world = generate_world(DEFAULT_WORLD)
    context = load_profile(PROFILE).context
    return render_frames_with_context(world, "waymo-5", context, FRAMES_SCALE, log="bench")


def _sweep_inputs(frames, index: int, cfg):
    """What `mvs._sweep_image` hands `_volume` for image `index` (offset 0): the prepared reference,
    sources and hypotheses (None where no source qualifies)."""
    from scube_sim.reconstruct.stereo import mvs
    from scube_sim.reconstruct.stereo.sweep import inverse_depth_hypotheses
    from scube_sim.reconstruct.stereo.views import candidates, select_sources

    ref = frames.images[index]
    boxes = {f.offset: f.boxes for f in frames.instants()}
    depths = inverse_depth_hypotheses(cfg.near_m, cfg.far_m, cfg.hypotheses)
    inv_step = (1.0 / cfg.near_m - 1.0 / cfg.far_m) / (cfg.hypotheses - 1)
    views = select_sources(ref, candidates(frames, index), cfg.sources, inv_step, min_baseline_m=cfg.min_baseline_m,
                           max_axis_angle_deg=cfg.max_axis_angle_deg, good_step_px=cfg.good_step_px / cfg.scale)
    if not views:
        return None
    ref_img, k_ref, ref_ok, hw, srcs = mvs._prepare(ref, views, boxes, cfg, cfg.scale, 0, None)
    return ref_img, k_ref, ref_ok, hw, srcs, views, depths, cfg


def _interleaved(fns: dict, repeats: int) -> tuple[dict, dict]:
    """Best seconds of each of `fns` (name -> callable) over `repeats` rounds, run in turn each
    round, and each one's last result."""
    sec, out = {}, {}
    for _ in range(repeats):
        for name, fn in fns.items():
            t = time.perf_counter()
            out[name] = fn()
            sec[name] = min(sec.get(name, np.inf), time.perf_counter() - t)
    return sec, out


def _with_core(core: str, fn):
    from scube_sim.raytrace.compiled import CORE_ENV

    def run():
        before = os.environ.get(CORE_ENV)
        os.environ[CORE_ENV] = core
        try:
            return fn()
        finally:
            if before is None:
                os.environ.pop(CORE_ENV, None)
            else:
                os.environ[CORE_ENV] = before
    return run


def _differing(a: np.ndarray, b: np.ndarray) -> float:
    return float(1 - ((a == b) | (np.isnan(a) & np.isnan(b))).mean())


def run(repeats: int, cameras: int | None = None) -> list[dict]:
    from scube_sim.converter.profile import load_profile
    from scube_sim.cpus import resolve_threads
    from scube_sim.reconstruct.stereo import compiled, mvs, stereo_depth

    if not compiled.available():
        raise SystemExit(f"the compiled stereo sweep is not built ({compiled.load_error()})")
    cfg = load_profile(PROFILE).evidence.stereo
    threads = resolve_threads()
    torch.set_num_threads(threads)
    t = time.perf_counter()
    frames = _frames()
    print(f"frames rendered in {time.perf_counter() - t:.1f} s; {threads} threads")
    rows = []
    for index, im in enumerate(frames.images[:cameras]):
        inputs = _sweep_inputs(frames, index, cfg)
        if inputs is None:
            continue
        vol, vol_out = _interleaved({"reference": lambda: mvs._volume_reference(*inputs, None),
                                     "compiled": lambda: compiled.volume(*inputs, None, threads=threads)}, repeats)
        depth_fn = lambda: stereo_depth(frames, index, cfg, movers=cfg.movers)  # noqa: E731
        e2e, e2e_out = _interleaved({"reference": _with_core("reference", depth_fn),
                                     "compiled": _with_core("compiled", depth_fn)}, repeats)
        a, b = vol_out["compiled"], vol_out["reference"]
        same = all(np.array_equal(x.numpy(), y.numpy(), equal_nan=True)
                   for x, y in zip([a[0], *a[1], *a[2], *a[3]], [b[0], *b[1], *b[2], *b[3]]))
        fast, slow = e2e_out["compiled"], e2e_out["reference"]
        rows.append({
            "camera": im.name, "pixels": f"{inputs[3][1]}x{inputs[3][0]}", "sources": len(inputs[5]),
            "hypotheses": int(cfg.hypotheses),
            "sweep_reference_s": round(vol["reference"], 3), "sweep_compiled_s": round(vol["compiled"], 3),
            "sweep_ratio": round(vol["reference"] / vol["compiled"], 1),
            "stereo_reference_s": round(e2e["reference"], 3), "stereo_compiled_s": round(e2e["compiled"], 3),
            "stereo_ratio": round(e2e["reference"] / e2e["compiled"], 1),
            "volume_same_bytes": same, "volume_differing": _differing(a[0].numpy(), b[0].numpy()),
            "depth_agree": round(1 - _differing(fast.depth, slow.depth), 4),
            "confidence_agree": round(1 - _differing(fast.confidence, slow.confidence), 4),
            "threads": threads,
        })
        print(rows[-1])
    total = {k: sum(r[k] for r in rows) for k in ("sweep_reference_s", "sweep_compiled_s", "stereo_reference_s",
                                                  "stereo_compiled_s")}
    rows.append({"camera": "all", "sources": sum(r["sources"] for r in rows),
                 **{k: round(v, 3) for k, v in total.items()},
                 "sweep_ratio": round(total["sweep_reference_s"] / total["sweep_compiled_s"], 1),
                 "stereo_ratio": round(total["stereo_reference_s"] / total["stereo_compiled_s"], 1),
                 "volume_same_bytes": all(r["volume_same_bytes"] for r in rows), "threads": threads})
    print(f"sweep: {rows[-1]['sweep_ratio']}x faster compiled; stereo_depth: {rows[-1]['stereo_ratio']}x")
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="two cameras, one repeat")
    args = ap.parse_args(argv)
    repeats = 1 if args.quick else args.repeats
    rows = run(repeats, 2 if args.quick else None)
    header = ["camera", "pixels", "sources", "hypotheses", "sweep_reference_s", "sweep_compiled_s", "sweep_ratio",
              "stereo_reference_s", "stereo_compiled_s", "stereo_ratio", "volume_same_bytes", "depth_agree",
              "confidence_agree"]
    write_results("stereo", rows, header,
                  notes=f"the demo world's frames (waymo-5 at the converter's image scale, +-4 instants), the "
                        f"{PROFILE} profile's stereo, per camera at T: the sweep (`_volume`) and `stereo_depth` "
                        f"(with the moving objects' own sweeps) on the torch reference and on the compiled sweep, "
                        f"interleaved, best of {repeats}, {rows[-1]['threads']} threads each; volume_same_bytes: "
                        "the volumes and each source's extremes equal; *_agree: share of pixels alike")


if __name__ == "__main__":
    main()
