#!/usr/bin/env bash
# Installs what pointfarm needs beyond the Rust toolchain: a Vulkan driver to render with.
# On machines without a GPU that is Mesa's lavapipe (software Vulkan, Debian package
# mesa-vulkan-drivers). Does nothing when a lavapipe driver is already installed.
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
$sudo apt-get update -qq
$sudo apt-get install -y -qq --no-install-recommends mesa-vulkan-drivers libvulkan1 >/dev/null
compgen -G "/usr/share/vulkan/icd.d/lvp_icd*.json" >/dev/null || {
    echo "pointfarm setup: mesa-vulkan-drivers installed but no lavapipe driver found" >&2
    exit 1
}
