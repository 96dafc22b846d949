#!/usr/bin/env bash
# The README's first command: from a fresh clone, render a turntable of a generated sample
# cloud to PNG frames in ./frames/.
set -euo pipefail
cd "$(dirname "$0")/.."

bash deploy/setup.sh
cargo build --release --locked --bin pointfarm
pointfarm=target/release/pointfarm
mkdir -p frames
"$pointfarm" sample frames/sample.laz
"$pointfarm" render frames/sample.laz --turntable 12 --size 1280x720 --point-size 2 --out frames/
echo "frames written to $(pwd)/frames/"
