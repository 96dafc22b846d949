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
# --pointfarm (or POINTFARM_BIN) is the binary measured, by default this tree's, built in debug
# (enough at 640x360); --before (or POINTFARM_BEFORE) an older build to compare with, left out when
# not given. Without inputs it renders the two real scans of the gallery, autzen_trim.laz and
# lone-star.laz in ${POINTFARM_DATA:-../shared/data}, and every .las/.laz file of laspy's tests:
# in $POINTFARM_LASPY_DATA when set (`bash deploy/test.sh` fetches them into target/laspy-data),
# else in ${LASPY_DATA:-../laspy/tests/data} (a laspy checkout beside this one:
# `git clone --depth 1 https://github.com/laspy/laspy ../laspy`).
# --images keeps the frames (NAME.after.png, NAME.before.png); otherwise they are discarded.
set -euo pipefail
here=$PWD
cd "$(dirname "$0")/.."
# Paths given on the command line are the caller's, from where it ran.
abs() { case $1 in /*) echo "$1" ;; *) echo "$here/$1" ;; esac; }

pointfarm=${POINTFARM_BIN:-}
before=${POINTFARM_BEFORE:-}
args=()
inputs=()
while [ $# -gt 0 ]; do
    case $1 in
        --pointfarm) pointfarm=$(abs "$2"); shift 2 ;;
        --before) before=$(abs "$2"); shift 2 ;;
        --images) args+=("$1" "$(abs "$2")"); shift 2 ;;
        --size | --runs) args+=("$1" "$2"); shift 2 ;;
        -h | --help) sed -n '2,18p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        -*) echo "gallery-figures: unknown option $1" >&2; exit 2 ;;
        *) inputs+=("$(abs "$1")"); shift ;;
    esac
done
if [ ${#inputs[@]} -eq 0 ]; then
    data=${POINTFARM_DATA:-../shared/data}
    laspy=${POINTFARM_LASPY_DATA:-${LASPY_DATA:-../laspy/tests/data}}
    inputs=("$data/autzen_trim.laz" "$data/lone-star.laz" "$laspy")
fi
for i in "${inputs[@]}"; do
    [ -e "$i" ] || { echo "gallery-figures: $i not found" >&2; exit 1; }
done
# The current tree's defaults unless told otherwise, so one command refreshes the table.
if [ -z "$pointfarm" ]; then
    cargo build --quiet --locked --bin pointfarm
    pointfarm=${CARGO_TARGET_DIR:-target}/debug/pointfarm
fi
[ -x "$pointfarm" ] || { echo "gallery-figures: no pointfarm binary at $pointfarm (cargo build --bin pointfarm)" >&2; exit 1; }
if [ -n "$before" ]; then
    [ -x "$before" ] || { echo "gallery-figures: no binary at $before" >&2; exit 1; }
    args+=(--before "$before")
fi

# The figures are computed in Rust; a debug build is quick enough for 640x360 frames.
cargo build --quiet --locked -p pointfarm-bench --bin gallery-figures
"${CARGO_TARGET_DIR:-target}/debug/gallery-figures" --pointfarm "$pointfarm" "${args[@]}" "${inputs[@]}"
