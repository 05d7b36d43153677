#!/usr/bin/env bash
# Runs every check and test of the project. Installs what it needs first, so it works on a
# fresh machine with a Rust toolchain. Usage: bash scripts/test.sh
set -euo pipefail
cd "$(dirname "$0")/.."

step() { printf '\n==> %s (disk: %s free, %s)\n' "$*" "$(df -h --output=avail . | tail -n 1 | tr -d ' ')" "$(date -u +%H:%M:%S)"; }

step "system packages"
# Rendering tests run on lavapipe (Mesa's CPU Vulkan driver) and on llvmpipe through OpenGL (EGL),
# which the server prefers where there is no GPU.
if ! ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1 || ! ldconfig -p | grep -q 'libvulkan.so.1' \
    || ! ls /usr/share/glvnd/egl_vendor.d/*mesa*.json >/dev/null 2>&1; then
    if [ "$(id -u)" = 0 ]; then apt_get="apt-get"; else apt_get="sudo apt-get"; fi
    export DEBIAN_FRONTEND=noninteractive
    $apt_get update -qq
    $apt_get install -y -qq mesa-vulkan-drivers libvulkan1 libegl1 libegl-mesa0 libgl1-mesa-dri >/dev/null
fi
ls /usr/share/vulkan/icd.d/
export NODEVICE_SELECT=1
# Servers started by the tests fill no scene cache in the background: that thread would only take
# the cores the tests use, and its allocations would blur the tests that watch a server's memory.
# (The scene cache itself stays on; server/service/tests/server/scene_cache.rs tests both.)
export ESRP_NO_GENERATE_AHEAD=true

step "toolchain"
cargo --version
rustc --version

step "format"
if cargo fmt --version >/dev/null 2>&1; then
    cargo fmt --all -- --check
else
    echo "rustfmt is not installed: skipping the format check (rustup component add rustfmt)"
fi

step "lint"
if cargo clippy --version >/dev/null 2>&1; then
    cargo clippy --workspace --all-targets --locked -- -D warnings
else
    echo "clippy is not installed: skipping the lint (rustup component add clippy); checking that every target compiles"
    cargo check --workspace --all-targets --locked
fi

step "client library docs (esrp-client: every intra-doc link resolves, with and without its features)"
RUSTDOCFLAGS="-D warnings" cargo doc -p esrp-client --no-deps --locked --no-default-features
RUSTDOCFLAGS="-D warnings" cargo doc -p esrp-client --no-deps --locked --all-features

step "module import cycles (esrp-core, esrp-server, esrp-client, esrp-render, esrp-dataset, esrp-planner)"
# No module imports one that imports it (ARCHITECTURE.md); the self-test first shows the check
# finds circles put in on purpose.
if ! command -v python3 >/dev/null 2>&1; then
    if [ "$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq python3 >/dev/null; else sudo apt-get update -qq && sudo apt-get install -y -qq python3 >/dev/null; fi
fi
python3 scripts/module_cycles.py --self-test server/core/src server/service/src clients/rust/src server/render/src \
    server/dataset/src server/planner/src

step "tests"
cargo test --workspace --locked

step "rendering tests on OpenGL (llvmpipe) too"
# `--workspace` keeps the features the tests above were built with, so nothing is rebuilt (with
# `-p esrp-render` alone cargo resolves other features and compiles wgpu again).
ESRP_RENDER_BACKEND=gl cargo test --workspace --locked --test render

# The benchmarks (criterion, in every crate's benches/) are compiled and linted by the clippy
# step's `--all-targets`; building them in the bench profile here too cost a whole optimised
# build of the workspace.

step "python: the client package (clients/python) and the dm_env_rpc end-to-end tests"
bash scripts/python-tests.sh

step "docker: the images against a Docker engine, compose and the Kubernetes manifests"
bash scripts/docker-tests.sh
