"""Validation figures of consecutive training runs (a run and the runs warm-started from it) on
one step axis, for a shipped checkpoint's README.

Each run's ``metrics.jsonl`` (one record per validation: ``step`` and ``val``) is shifted by the
steps of the runs before it; the dashed lines mark where each later run began.

Run: ``python tools/plot_training_runs.py RUN1/metrics.jsonl:320 RUN2/metrics.jsonl:320
--metrics psnr_t0 ssim_t0 psnr_sky_t0 -o val.png`` (``:N`` is that run's length in steps).
``--overlay --labels A B`` draws runs of the same length side by side instead (each from step 0),
for variants trained at one budget.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def read_runs(specs: list[str], overlay: bool = False) -> list[tuple[str, int, list[dict]]]:
    """(path, first step, records) per ``PATH:STEPS`` spec, in order (every first step 0 with
    `overlay`)."""
    runs, offset = [], 0
    for spec in specs:
        path, _, steps = spec.rpartition(":")
        if not path or not steps.isdigit():
            raise SystemExit(f"{spec}: expected METRICS.jsonl:STEPS (the run's length in steps)")
        lines = Path(path).read_text().splitlines()
        records = [json.loads(line) for line in lines if line.strip()]
        runs.append((path, offset, records))
        offset += 0 if overlay else int(steps)
    return runs


def plot(runs: list[tuple[str, int, list[dict]]], metrics: list[str], out: Path,
         labels: list[str] | None = None) -> Path:
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.2 * len(metrics), 3.4), squeeze=False)
    for ax, key in zip(axes[0], metrics):
        for i, (path, offset, records) in enumerate(runs):
            pts = [(offset + r["step"], r["val"][key]) for r in records if key in r.get("val", {})]
            if offset:
                ax.axvline(offset, color="0.6", ls="--", lw=1)
            if pts:
                ax.plot(*zip(*pts), "o-", label=labels[i] if labels else f"run {i + 1}")
        ax.set_title(key)
        ax.set_xlabel("step" if labels else "step (all runs)")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="METRICS.jsonl:STEPS, in the order the runs were made")
    ap.add_argument("--metrics", nargs="+", default=["psnr_t0"])
    ap.add_argument("--overlay", action="store_true", help="every run from step 0 (variants at one budget)")
    ap.add_argument("--labels", nargs="+", default=None, help="with --overlay: a legend label per run")
    ap.add_argument("-o", "--output", type=Path, required=True)
    args = ap.parse_args()
    if args.labels and (not args.overlay or len(args.labels) != len(args.runs)):
        ap.error("--labels goes with --overlay, one per run")
    print(plot(read_runs(args.runs, args.overlay), args.metrics, args.output, args.labels))


if __name__ == "__main__":
    main()
