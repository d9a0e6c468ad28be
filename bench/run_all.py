"""`make bench`: every benchmark in turn (results in bench/results/)."""

from __future__ import annotations

import sys

from . import bench_tracer


def main() -> None:
    quick = "--quick" in sys.argv
    sys.argv = [sys.argv[0]] + (["--quick"] if quick else [])
    bench_tracer.main()


if __name__ == "__main__":
    main()
