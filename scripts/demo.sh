#!/usr/bin/env bash
# The main job: builds esrp-server, starts it on the built-in benchmark esrp-bench-v2 (on a free
# local port, rendering on the GPU or on lavapipe), and runs a short evaluation against it over
# gRPC: the expert and a random agent on a few test scenes, printing SR / OSR / RDR.
# Usage: bash scripts/demo.sh [SCENES]   (default 6)
set -euo pipefail
cd "$(dirname "$0")/.."
scenes="${1:-6}"

# Without a GPU the server renders on Mesa's CPU renderer: llvmpipe through OpenGL (EGL), or
# lavapipe through Vulkan.
if ! ls /usr/share/vulkan/icd.d/*.json >/dev/null 2>&1 || ! ldconfig -p | grep -q 'libvulkan.so.1' \
    || ! ls /usr/share/glvnd/egl_vendor.d/*mesa*.json >/dev/null 2>&1; then
    if [ "$(id -u)" = 0 ]; then apt_get="apt-get"; else apt_get="sudo apt-get"; fi
    export DEBIAN_FRONTEND=noninteractive
    $apt_get update -qq
    $apt_get install -y -qq mesa-vulkan-drivers libvulkan1 libegl1 libegl-mesa0 libgl1-mesa-dri >/dev/null
fi
export NODEVICE_SELECT=1

cargo build --release --locked -q -p esrp-server -p esrp-client --bins
# esrp-demo starts target/release/esrp-server itself and stops it when done.
./target/release/esrp-demo --scenes "$scenes"
