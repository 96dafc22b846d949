#!/usr/bin/env bash
# Renders the gallery in docs/gallery/: the same real scan in every mode, so anyone can
# compare them and rerun this after a change. Needs the real scans in ../shared/data/. Each
# image names its shading, so the default's does not blur the modes apart.
set -euo pipefail
cd "$(dirname "$0")/.."

data=${POINTFARM_DATA:-../shared/data}
scan="$data/autzen_trim.laz"
tls="$data/lone-star.laz"
for f in "$scan" "$tls"; do
    [ -f "$f" ] || { echo "gallery: $f not found (set POINTFARM_DATA)" >&2; exit 1; }
done

bash deploy/setup.sh
cargo build --release --locked --bin pointfarm
pf=target/release/pointfarm
out=docs/gallery
mkdir -p "$out"
common=(--size 640x360 --point-size 2)

render() { # name, file, options...
    local name=$1 file=$2
    shift 2
    "$pf" render "$file" --out "$out/$name.png" "${common[@]}" "$@" >/dev/null
    echo "$out/$name.png"
}

render autzen-basic "$scan" --shading none
render autzen-high "$scan" --quality high --shading none
render autzen-high-edl "$scan" --quality high --shading edl
render autzen-ssaa "$scan" --quality high --supersample 2 --shading none
render autzen-intensity "$scan" --color intensity --quality high --shading none
render autzen-elevation "$scan" --color elevation --quality high --shading none
render autzen-classification "$scan" --color classification --quality high --shading none
render autzen-return "$scan" --color return --quality high --shading none
render lone-star-intensity "$tls" --quality high --shading none
render lone-star-edl "$tls" --quality high --shading edl --color "#d8d2c4"
render autzen-fill-edl "$scan" --fill --shading edl
render autzen-fill-pintus "$scan" --fill --shading pintus
render lone-star-fill-pintus "$tls" --fill --shading pintus --color "#d8d2c4"
