#!/usr/bin/env bash
# The README's second command: install what the tests need, then run every test.
# GPU tests run on whatever adapter pointfarm picks (lavapipe on machines without a GPU).
set -euo pipefail
cd "$(dirname "$0")/.."

bash deploy/setup.sh
cargo test --workspace --locked
