#!/usr/bin/env bash
# The README's second command: install what the tests need, then run every test and the lints.
# GPU tests run on whatever adapter pointfarm picks (lavapipe on machines without a GPU).
set -euo pipefail
cd "$(dirname "$0")/.."

bash deploy/setup.sh
cargo test --workspace --locked
# Lints, where the toolchain has them (rustup's default profile does).
if cargo fmt --version >/dev/null 2>&1; then
    cargo fmt --all -- --check
fi
if cargo clippy --version >/dev/null 2>&1; then
    cargo clippy --workspace --all-targets --locked -- -D warnings
fi
