#!/usr/bin/env bash
# Installs what pointfarm needs beyond the Rust toolchain: a Vulkan driver to render with.
# On machines without a GPU that is Mesa's lavapipe (software Vulkan, Debian package
# mesa-vulkan-drivers; on Debian 12 from bookworm-backports). Does nothing when a lavapipe
# driver is already installed.
set -euo pipefail

if compgen -G "/usr/share/vulkan/icd.d/lvp_icd*.json" >/dev/null; then
    exit 0
fi

echo "pointfarm setup: installing Mesa's lavapipe (mesa-vulkan-drivers)" >&2
if ! command -v apt-get >/dev/null; then
    echo "pointfarm setup: no apt-get here; install Mesa's Vulkan drivers (lavapipe) with your package manager" >&2
    exit 1
fi
sudo=""
if [ "$(id -u)" -ne 0 ]; then
    sudo="sudo"
fi
export DEBIAN_FRONTEND=noninteractive
packages=(mesa-vulkan-drivers libvulkan1)
installed=""
# Debian 12 ships Mesa 22.3, whose lavapipe runs pointfarm's passes slower than the Mesa 25
# of Debian 13, which bookworm-backports carries too (BENCHMARKS.md): on Debian 12 lavapipe
# comes from there, unless POINTFARM_MESA=stock. Any failure falls back to bookworm's own.
codename=$(. /etc/os-release 2>/dev/null && echo "${VERSION_CODENAME:-}") || codename=""
if [ "$codename" = bookworm ] && [ "${POINTFARM_MESA:-backports}" != stock ]; then
    if ! grep -rqs "bookworm-backports" /etc/apt/sources.list /etc/apt/sources.list.d/; then
        echo "deb http://deb.debian.org/debian bookworm-backports main" |
            $sudo tee /etc/apt/sources.list.d/pointfarm-bookworm-backports.list >/dev/null
    fi
    if $sudo apt-get update -qq &&
        $sudo apt-get install -y -qq --no-install-recommends -t bookworm-backports "${packages[@]}" >/dev/null; then
        installed=backports
    else
        echo "pointfarm setup: lavapipe from bookworm-backports failed; installing bookworm's" >&2
    fi
fi
if [ -z "$installed" ]; then
    $sudo apt-get update -qq
    $sudo apt-get install -y -qq --no-install-recommends "${packages[@]}" >/dev/null
fi
compgen -G "/usr/share/vulkan/icd.d/lvp_icd*.json" >/dev/null || {
    echo "pointfarm setup: mesa-vulkan-drivers installed but no lavapipe driver found" >&2
    exit 1
}
