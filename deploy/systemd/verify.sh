#!/usr/bin/env bash
# Checks the systemd units with `systemd-analyze verify` (no running systemd needed): the
# units as installed, in a scratch root with this machine's own system units and the
# pointfarm binary built here at /usr/local/bin/pointfarm. Any complaint (an unknown key, a
# value that does not parse) fails the check, not only the ones systemd-analyze exits on.
#
#   bash deploy/systemd/verify.sh [BINARY]   # default: target/release/pointfarm, else target/debug/pointfarm
set -euo pipefail
cd "$(dirname "$0")/../.."

if ! command -v systemd-analyze >/dev/null; then
    echo "systemd: skipping the units' check: no systemd-analyze here (apt-get install systemd)" >&2
    exit 0
fi
target="${CARGO_TARGET_DIR:-target}"
binary=${1:-}
if [ -z "$binary" ]; then
    for candidate in "$target/release/pointfarm" "$target/debug/pointfarm"; do
        if [ -x "$candidate" ]; then binary=$candidate; break; fi
    done
fi
if [ -z "$binary" ] || [ ! -x "$binary" ]; then
    echo "systemd: no pointfarm binary to check the units with; build one first (cargo build --bin pointfarm)" >&2
    exit 1
fi

root=$(mktemp -d)
trap 'rm -rf "$root"' EXIT
mkdir -p "$root/etc/systemd/system" "$root/usr/local/bin" "$root/usr/lib/systemd"
cp -r /usr/lib/systemd/system "$root/usr/lib/systemd/"
cp deploy/systemd/*.service "$root/etc/systemd/system/"
ln "$binary" "$root/usr/local/bin/pointfarm" 2>/dev/null || cp "$binary" "$root/usr/local/bin/pointfarm"

units=(pointfarm.service pointfarm-worker@0.service pointfarm-worker@1.service)
status=0
output=$(cd "$root" && systemd-analyze verify --root="$root" "${units[@]}" 2>&1) || status=$?
if [ "$status" -ne 0 ] || [ -n "$output" ]; then
    echo "systemd: the units do not verify:" >&2
    echo "${output//$root/}" >&2
    exit 1
fi
echo "systemd: ${units[*]} verify (systemd $(systemd-analyze --version | awk 'NR == 1 { print $2 }'))"
