"""`make bench`: every benchmark in turn (results in bench/results/)."""

from __future__ import annotations

import sys

from . import (
    bench_batch,
    bench_conversion,
    bench_fidelity,
    bench_fusion,
    bench_render,
    bench_representation,
    bench_sim,
    bench_sparse,
    bench_stereo,
    bench_tracer,
    bench_voxel_cast,
)


def main() -> None:
    quick = "--quick" in sys.argv
    for module in (bench_tracer, bench_representation, bench_sim, bench_fidelity, bench_sparse, bench_render, bench_batch):
        sys.argv = [sys.argv[0]] + (["--quick"] if quick else [])
        module.main()
    bench_voxel_cast.main(["--repeats", "1" if quick else "2"])
    bench_fusion.main(["--repeats", "1" if quick else "2"])
    bench_stereo.main(["--quick"] if quick else [])
    bench_conversion.main(["--quick"] if quick else [])


if __name__ == "__main__":
    main()
