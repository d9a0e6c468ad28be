#!/usr/bin/env bash
# Checksums of the outputs a refactor must leave byte-identical: the demo's scene.npz, sweep.pcd and
# converted.npz; every data file of a worlds sample; the point-cloud and USD files of two short
# replays (manifests record times: left out); a `scube-sim convert` of a worlds sample on one thread.
# Usage: tools/behaviour_checksums.sh WORKDIR > checksums.txt   (about 5 minutes on 2 cores)
set -euo pipefail
work=${1:?usage: $0 WORKDIR}
here=$(cd "$(dirname "$0")/.." && pwd)
cli="$here/.venv/bin/scube-sim"
rm -rf "$work" && mkdir -p "$work"
cd "$work"
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
"$cli" demo -o demo >/dev/null
"$cli" worlds generate --split test --count 1 -o worlds >/dev/null
"$cli" replay "$here/scenarios/converted-drive.yaml" -o replay-converted --duration 0.5 >/dev/null
"$cli" replay "$here/scenarios/multi-lidar.yaml" -o replay-multi --duration 0.3 >/dev/null
"$cli" convert worlds/test/000000 -o convert/converted.npz >/dev/null
{
  sha256sum demo/scene.npz demo/sweep.pcd demo/converted.npz
  find worlds -type f ! -name 'manifest.json' ! -name 'batch.json' ! -path '*/.batch/*' | sort | xargs sha256sum
  find replay-converted replay-multi convert -type f \( -name '*.pcd' -o -name '*.npz' -o -name '*.bin' \
    -o -name '*.usd*' \) | sort | xargs sha256sum
} | sed "s#  # #"
