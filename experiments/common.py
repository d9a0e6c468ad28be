"""The experiments' result files: experiments/results/<name>.json and .md, written as the
benchmarks write theirs (`bench.common.write_results`)."""

from __future__ import annotations

from pathlib import Path

from bench.common import write_results as _write_results

EXPERIMENTS_DIR = Path(__file__).resolve().parent
RESULTS = EXPERIMENTS_DIR / "results"
RUNS = EXPERIMENTS_DIR.parent / "runs"  # work files, not committed (.gitignore)


def write_results(name: str, rows: list[dict], header: list[str], notes: str = "") -> Path:
    """experiments/results/<name>.json (all fields) and <name>.md (the `header` columns)."""
    return _write_results(name, rows, header, notes, results=RESULTS)
