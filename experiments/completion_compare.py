"""Learned completions compared on one measurement per sample (issue 45: the deterministic network
against the latent diffusion at the same budget, a new checkpoint against the shipped one).

Per worlds sample: the evidence is measured once with the profile's settings
(`reconstruct.evidence.measure_evidence`), then each checkpoint's converter builds its scene from that
measurement (`Converter.convert(..., evidence=)`) and `eval sensor-to-sensor`'s `evaluate_sample`
scores it (HDL-64E at the input pose, 20 m and 60 m ahead, against the mesh; the ground-truth
sweeps regenerated once). The evidence alone is scored once: it is the same scene for every
checkpoint. Stereo, the costly part, runs once a sample instead of once per checkpoint.

    python -m experiments.completion_compare --data DIR [--split test] [--limit 40] [--profile evidence] \\
        --checkpoint shipped=completion-cpu --checkpoint direct=runs/completion-v2/last.pt [--name NAME] \\
        [--shard I/N] [--merge direct.footprint_height_m=0]

`--merge NAME.FIELD=VALUE` sets one of the merge's settings (`converter.merge.CompletionConfig`;
VALUE read as JSON) for the checkpoint of that NAME: the same network under two merges is two
NAMEs of one checkpoint.

Writes experiments/results/<NAME>.{json,md} (default completion_compare): per checkpoint and
distance ahead the ray-weighted rows of `eval sensor-to-sensor` (median |dr|, p90, share of the
mesh's returns returned) and the completion grid's IoU / mIoU against the truth at 0.8 m; and ray
by ray against the evidence alone (`paired`): of the mesh's returns on each split, the share the
completion makes worse or better by over `CHANGED_M`, among the rays both scenes return; the share
it returns where the evidence alone returned nothing, and their median |dr|; the share it loses,
and the evidence alone's median |dr| on those. A median over a split mixes rays of both kinds, so
a completion that returns rays the evidence missed, at larger errors than the easy rays it already
returned, moves the median without making a ray worse: the ray-by-ray figures tell the two apart.

The LiDAR is driven straight along the ego's heading, and where the road bends the pose 20 or 60 m
on can stand inside or against a building. So both tables are given again over the poses a car
can stand at (`converter.eval.sensor_to_sensor.pose_clear`: the ego's box, grown by 1 m sideways and
lengthways, holds none of the truth's object voxels).

Each sample's result is kept in runs/compare/<NAME>/<sample>.json as soon as it is measured (with
the checkpoints it was measured for; a file for other checkpoints is measured again), so an
interrupted run resumes, and `--shard I/N` measures every N-th sample from the I-th: N processes
with the same NAME share the samples, and each writes the table from every sample measured so far
(the one that finishes last writes the whole; the table says how many of the samples it holds).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from rich.progress import track

from experiments.common import RESULTS, RUNS
from scube_sim.atomic import atomic_path
from scube_sim.camera.frames import chunk_to_world
from scube_sim.converter.eval import sensor_to_sensor as s2s
from scube_sim.converter.frames import open_frames
from scube_sim.converter.merge import CompletionConfig
from scube_sim.converter.pipeline import Converter
from scube_sim.converter.profile import load_profile
from scube_sim.reconstruct.evidence import measure_evidence
from scube_sim.transforms import invert_pose

ALONE = s2s.SCENES[1]
CHANGED_M = 0.5  # a ray's |dr| grown (shrunk) by more than this: made worse (better)
PAIRED_COUNTS = ("rays", "both", "worse", "better", "gained", "lost")
GRID_KEYS = ("completion_iou", "completion_miou", "completion_added_cells", "completion_removed_share",
             "completion_s")


def paired(reference: np.ndarray, rays: np.ndarray, alone: np.ndarray, completed: np.ndarray) -> dict:
    """Ray by ray (module docstring), the completed sweep against the evidence alone's: range images
    (rings, columns; NaN: no return), `rays` (rings, columns) bool the reference's returns compared.
    Counts (`PAIRED_COUNTS`), the median |dr| (m) of the gained rays and the evidence alone's median
    |dr| on the lost ones (NaN: none)."""
    a, c = rays & np.isfinite(alone), rays & np.isfinite(completed)
    both, gained, lost = a & c, c & ~a, a & ~c
    err_a, err_c = np.abs(alone - reference), np.abs(completed - reference)
    return {"rays": int(rays.sum()), "both": int(both.sum()),
            "worse": int((both & (err_c > err_a + CHANGED_M)).sum()),
            "better": int((both & (err_a > err_c + CHANGED_M)).sum()),
            "gained": int(gained.sum()), "lost": int(lost.sum()),
            "gained_median_m": float(np.median(err_c[gained])) if gained.any() else float("nan"),
            "lost_median_m": float(np.median(err_a[lost])) if lost.any() else float("nan")}


def clear_only(samples: list[dict]) -> list[dict]:
    """The samples with only the ray-by-ray rows of the poses a car can stand at (each sample's
    ``pose_clear``, as `eval sensor-to-sensor` gives it)."""
    return [{**s, "paired": {n: [r for r in rs if s["pose_clear"][f"{r['ahead_m']:g}"]]
                             for n, rs in s.get("paired", {}).items()}} for s in samples]


def measure_sample(d: Path, base, convs: dict, lidar, cache: dict) -> dict:
    """One sample's rows (the truth, the evidence alone, each checkpoint by name), grid stages and
    ray-by-ray figures against the evidence alone (`paired`: per checkpoint, rows by ahead and split)."""
    frames = open_frames(d, context=base.context)
    t0 = time.perf_counter()
    ev = measure_evidence(frames, invert_pose(chunk_to_world(frames)), base.evidence)
    rows, measure_s, stages, pairs = [], time.perf_counter() - t0, {}, {}
    for k, (name, conv) in enumerate(convs.items()):
        sweeps: dict = {}
        res = s2s.evaluate_sample(conv, d, lidar, gt_cache=cache, convert_options={"evidence": ev},
                                  with_psnr=False, sweeps=sweeps)
        for r in res["rows"]:
            if r["scene"] == "converted":
                rows.append({**r, "scene": name})
            elif k == 0:  # the truth and the evidence alone: the same for every checkpoint
                rows.append(r)
        stages[name] = {key: float(res["stages"].get(key, np.nan)) for key in GRID_KEYS}
        refs = cache[str(d.resolve())]
        pairs[name] = [{"ahead_m": p.ahead, "split": split,
                        **paired(ref["img"], mask, sweeps[(ALONE, p.ahead)], sweeps[("converted", p.ahead)])}
                       for ref, p in zip(refs["refs"], refs["poses"]) for split, mask in ref["masks"].items()]
    return {"sample": d.name, "measure_s": measure_s, "rows": rows, "stages": stages, "paired": pairs}


def summarise_paired(samples: list[dict], names) -> list[dict]:
    """Per checkpoint, distance ahead and split: the samples' counts summed, the gained and the lost
    rays' median |dr| averaged weighted by their counts."""
    groups: dict[tuple, list[dict]] = {}
    for s in samples:
        for name in names:
            for r in s.get("paired", {}).get(name, []):
                groups.setdefault((name, r["ahead_m"], r["split"]), []).append(r)
    out = []
    for (name, ahead, split), rs in groups.items():
        row = {"scene": name, "ahead_m": ahead, "split": split,
               **{k: int(sum(r[k] for r in rs)) for k in PAIRED_COUNTS}}
        for kind in ("gained", "lost"):
            w = np.array([r[kind] for r in rs], np.float64)
            v = np.array([r.get(f"{kind}_median_m", np.nan) for r in rs], np.float64)
            ok = np.isfinite(v) & (w > 0)
            row[f"{kind}_median_m"] = float(np.average(v[ok], weights=w[ok])) if ok.any() else float("nan")
        out.append(row)
    return out


def compare(data: Path, split: str, limit: int | None, profile: str, checkpoints: dict[str, str],
            work: Path, shard: tuple[int, int] = (0, 1), merges: dict[str, dict] | None = None) -> dict:
    """-> {"rows": summarised over the samples measured so far (scenes: the truth, the evidence
    alone, each checkpoint by name), "grid": per checkpoint the stages' means, "samples": per
    sample}; this process measures the samples of its `shard` (I, N) not yet in `work`; `merges`: per
    checkpoint name, merge settings other than the defaults."""
    base = load_profile(profile)
    merges = merges or {}
    convs = {name: Converter(base.model_copy(update={"name": f"{base.name}+{name}", "completion": CompletionConfig(
                 checkpoint=ck, **merges.get(name, {}))}))
             for name, ck in checkpoints.items()}
    lidar = s2s.geometric_lidar("hdl64e")
    dirs = sorted(d for d in (Path(data) / split).iterdir() if (d / "meta.json").is_file())[:limit]
    key = {"data": str(Path(data).resolve()), "split": split, "profile": profile, "checkpoints": checkpoints,
           **({"merges": merges} if merges else {})}
    work.mkdir(parents=True, exist_ok=True)

    def done(d: Path) -> dict | None:
        f = work / f"{d.name}.json"
        if not f.is_file():
            return None
        got = json.loads(f.read_text(encoding="utf-8"))
        return got if got.get("key") == key else None

    cache: dict = {}
    mine = [d for d in dirs[shard[0]::shard[1]] if done(d) is None]
    for d in track(mine, description=f"{split} samples, shard {shard[0]}/{shard[1]}"):
        res = {"key": key, **measure_sample(d, base, convs, lidar, cache)}
        with atomic_path(work / f"{d.name}.json") as tmp:
            Path(tmp).write_text(json.dumps(res), encoding="utf-8")
    samples = [s for s in (done(d) for d in dirs) if s is not None]
    for s in samples:  # measured before the eval gave it: from the truth's voxels, as the eval does
        with np.load(Path(data) / split / s["sample"] / "voxels.npz") as z:
            vox = {k: z[k] for k in ("coarse_ijk", "coarse_labels", "coarse_voxel_size")}
        s["pose_clear"] = {f"{a:g}": s2s.pose_clear(vox, a) for a in sorted({r["ahead_m"] for r in s["rows"]})}
    grid = {name: {k: float(np.nanmean([s["stages"][name][k] for s in samples])) for k in GRID_KEYS}
            for name in checkpoints}
    return {"split": split, "profile": profile, "checkpoints": checkpoints, "merges": merges, "samples_n": len(samples),
            "samples_of": len(dirs), "rows": s2s.summarise_rows(samples), "grid": grid,
            "paired": summarise_paired(samples, checkpoints),
            "clear_poses": {a: sum(s["pose_clear"][a] for s in samples) for a in samples[0]["pose_clear"]},
            "clear": {"rows": s2s.clear_rows(samples), "paired": summarise_paired(clear_only(samples), checkpoints)},
            "samples": samples}


def rows_table(rows: list[dict], names: list[str]) -> list[str]:
    """Markdown: per distance ahead and split, each scene's median |dr| / p90 / returns."""
    lines = ["| ahead | rays | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    by = {(r["ahead_m"], r["split"], r["scene"]): r for r in rows}
    for ahead, split in dict.fromkeys((r["ahead_m"], r["split"]) for r in rows):
        cells = []
        for n in names:
            r = by.get((ahead, split, n))
            cells.append("-" if r is None else f"{r['median_m']:.3f} / {r['p90_m']:.2f} / {100 * r['hit_agreement']:.1f} %")
        lines.append(f"| {ahead:.0f} m {split} | {by.get((ahead, split, ALONE), {}).get('rays', '-')} | "
                     + " | ".join(cells) + " |")
    return lines


def paired_table(paired_rows: list[dict], names: list[str]) -> list[str]:
    """Markdown: per distance ahead and split, each checkpoint's ray-by-ray shares (`paired`)."""
    lines = [f"Ray by ray against the evidence alone, shares of the mesh's returns: made worse / better by "
             f"over {CHANGED_M} m (both return) ; returned where the evidence alone returned nothing "
             f"(their median |dr|) ; no longer returned (the evidence alone's median |dr| on them).", "",
             "| ahead | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    pb = {(r["ahead_m"], r["split"], r["scene"]): r for r in paired_rows}
    for ahead, split in dict.fromkeys((r["ahead_m"], r["split"]) for r in paired_rows):
        cells = []
        for n in names:
            r = pb.get((ahead, split, n))
            if r is None:
                cells.append("-")
                continue
            pct = {k: 100 * r[k] / max(r["rays"], 1) for k in PAIRED_COUNTS}
            cells.append(f"{pct['worse']:.2f} / {pct['better']:.2f} % ; {pct['gained']:.2f} % "
                         f"({r['gained_median_m']:.2f} m) ; {pct['lost']:.2f} % ({r['lost_median_m']:.2f} m)")
        lines.append(f"| {ahead:.0f} m {split} | " + " | ".join(cells) + " |")
    return lines


def table(res: dict) -> list[str]:
    names = [ALONE, *res["checkpoints"]]
    lines = [f"# Completions on one measurement: {res['samples_n']} {res['split']} worlds"
             f" (of {res.get('samples_of', res['samples_n'])}), profile {res['profile']}",
             "", "HDL-64E against the mesh; median |dr| m / p90 m / share of the mesh's returns returned.", "",
             *rows_table(res["rows"], names)]
    lines += ["", "| checkpoint | " + " | ".join(GRID_KEYS) + " |", "|---|" + "---|" * len(GRID_KEYS)]
    for name, g in res["grid"].items():
        merge = "".join(f", {k} {v}" for k, v in res.get("merges", {}).get(name, {}).items())
        lines.append(f"| {name} ({res['checkpoints'][name]}{merge}) | " + " | ".join(f"{g[k]:.4g}" for k in GRID_KEYS) + " |")
    if res.get("paired"):
        lines += ["", *paired_table(res["paired"], list(res["checkpoints"]))]
    if res.get("clear"):
        counts = ", ".join(f"{n} at {a} m" for a, n in res["clear_poses"].items())
        lines += ["", f"## The poses a car can stand at ({counts} of {res['samples_n']}: the ego's box and "
                      f"{s2s.CLEAR_MARGIN_M:g} m around it free of the truth's objects)", "",
                  *rows_table(res["clear"]["rows"], names), "",
                  *paired_table(res["clear"]["paired"], list(res["checkpoints"]))]
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--split", default="test")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--profile", default="evidence", help="the evidence settings measured with")
    ap.add_argument("--checkpoint", action="append", required=True, metavar="NAME=CHECKPOINT",
                    help="a completion checkpoint (path or shipped name) and its name in the table; repeatable")
    ap.add_argument("--name", default="completion_compare")
    ap.add_argument("--shard", default="0/1", metavar="I/N", help="measure every N-th sample from the I-th")
    ap.add_argument("--merge", action="append", default=[], metavar="NAME.FIELD=VALUE",
                    help="a merge setting for the checkpoint NAME (VALUE as JSON); repeatable")
    args = ap.parse_args(argv)
    i, sep, n = args.shard.partition("/")
    if not (sep and i.isdigit() and n.isdigit() and 0 <= int(i) < int(n)):
        ap.error(f"--shard: expected I/N with 0 <= I < N, got {args.shard!r}")
    checkpoints = {}
    for item in args.checkpoint:
        name, sep, ck = item.partition("=")
        if not sep or not name or not ck or name in checkpoints or name == ALONE:
            ap.error(f"--checkpoint: expected NAME=CHECKPOINT with a new NAME, got {item!r}")
        checkpoints[name] = ck
    merges: dict[str, dict] = {}
    for item in args.merge:
        target, sep, value = item.partition("=")
        name, dot, field = target.partition(".")
        if not (sep and dot and name in checkpoints and field in CompletionConfig.model_fields):
            ap.error(f"--merge: expected NAME.FIELD=VALUE with a --checkpoint NAME and a field of "
                     f"CompletionConfig, got {item!r}")
        try:
            merges.setdefault(name, {})[field] = json.loads(value)
        except json.JSONDecodeError:
            merges.setdefault(name, {})[field] = value
    for name, fields in merges.items():
        try:
            CompletionConfig(checkpoint=checkpoints[name], **fields)
        except ValueError as e:
            ap.error(f"--merge for {name!r}: {e}")
    res = compare(args.data, args.split, args.limit, args.profile, checkpoints, RUNS / "compare" / args.name,
                  (int(i), int(n)), merges)
    RESULTS.mkdir(exist_ok=True)
    for suffix, text in ((".json", json.dumps(res, indent=1)), (".md", "\n".join(table(res)) + "\n")):
        with atomic_path(RESULTS / f"{args.name}{suffix}") as tmp:
            Path(tmp).write_text(text, encoding="utf-8")
    print("\n".join(table(res)))


if __name__ == "__main__":
    main()
