#!/usr/bin/env bash
# The README's first command: from a fresh clone, run the render service end to end in one
# command (the daemon and its supervised worker process on a loopback port) on a generated
# sample cloud, and write a 12-frame turntable to ./frames/.
set -euo pipefail
cd "$(dirname "$0")/.."

bash deploy/setup.sh
cargo build --release --locked --bin pointfarm
target/release/pointfarm demo --out frames --frames 12 --size 1280x720
echo "frames written to $(pwd)/frames/"
