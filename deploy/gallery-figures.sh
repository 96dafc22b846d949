#!/usr/bin/env bash
# What a render with no flags gives someone who knows nothing of the scan: per file, how much of
# the frame the subject fills, where it sits and how much of its silhouette the points light,
# for the current defaults beside an older binary's, and what EDL shading would cost by default.
# Prints the markdown table of docs/gallery.md on standard output (progress on standard error).
# Not part of the tests: it renders every file several times and its numbers are the machine's.
#
#   bash deploy/gallery-figures.sh [--pointfarm BIN] [--before OLD_BIN] [--size WxH] [--runs N]
#       [--images DIR] [FILE|FOLDER ...]
#
# --pointfarm (or POINTFARM_BIN) is the binary measured, by default target/debug/pointfarm built
# from this tree; --before (or POINTFARM_BEFORE) an older build to compare with, left out when
# not given. Without inputs it renders the real scans of ${POINTFARM_DATA:-../shared/data}
# and laspy's test files in ${LASPY_DATA:-../gallery-scratch/laspy/tests/data}; fetch those with
#
#   git clone --filter=blob:none --no-checkout https://github.com/laspy/laspy /tmp/laspy
#   git -C /tmp/laspy archive HEAD $(git -C /tmp/laspy ls-tree -r --name-only HEAD tests/data |
#       grep -iE '\.la[sz]$') | tar -x -C DIR        # then LASPY_DATA=DIR/tests/data
#
# (only the .las/.laz files: one of the folder's other files is missing from some mirrors).
# --images keeps the frames (NAME.after.png, NAME.before.png); otherwise they are discarded.
set -euo pipefail
cd "$(dirname "$0")/.."

pointfarm=${POINTFARM_BIN:-target/debug/pointfarm}
before=${POINTFARM_BEFORE:-}
args=()
inputs=()
while [ $# -gt 0 ]; do
    case $1 in
        --pointfarm) pointfarm=$2; shift 2 ;;
        --before) before=$2; shift 2 ;;
        --size | --runs | --images) args+=("$1" "$2"); shift 2 ;;
        -h | --help) sed -n '2,23p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        -*) echo "gallery-figures: unknown option $1" >&2; exit 2 ;;
        *) inputs+=("$1"); shift ;;
    esac
done
if [ ${#inputs[@]} -eq 0 ]; then
    inputs=("${POINTFARM_DATA:-../shared/data}" "${LASPY_DATA:-../gallery-scratch/laspy/tests/data}")
fi
for i in "${inputs[@]}"; do
    [ -e "$i" ] || { echo "gallery-figures: $i not found" >&2; exit 1; }
done
[ -x "$pointfarm" ] || { echo "gallery-figures: no pointfarm binary at $pointfarm (cargo build --bin pointfarm)" >&2; exit 1; }
if [ -n "$before" ]; then
    [ -x "$before" ] || { echo "gallery-figures: no binary at $before" >&2; exit 1; }
    args+=(--before "$before")
fi

# The figures are computed in Rust; a debug build is quick enough for 640x360 frames.
cargo build --quiet --locked -p pointfarm-bench --bin gallery-figures
"${CARGO_TARGET_DIR:-target}/debug/gallery-figures" --pointfarm "$pointfarm" "${args[@]}" "${inputs[@]}"
