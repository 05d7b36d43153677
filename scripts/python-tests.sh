#!/usr/bin/env bash
# Runs the Python end-to-end tests (tests/python): dm_env_rpc's compliance suites and whole
# DmEnvAdaptor episodes against the real esrp-server binary. Creates .venv (gitignored) with the
# pinned packages, builds the binaries, then runs ruff, mypy and pytest. Works on a fresh machine
# with a Rust toolchain; installs python3-venv (and the CPU Vulkan driver) if they are missing.
# Usage: bash scripts/python-tests.sh [PYTEST ARGS...]
set -euo pipefail
cd "$(dirname "$0")/.."

step() { printf '\n==> %s\n' "$*"; }

apt_install() {
    if [ "$(id -u)" = 0 ]; then apt_get="apt-get"; else apt_get="sudo apt-get"; fi
    export DEBIAN_FRONTEND=noninteractive
    $apt_get update -qq
    $apt_get install -y -qq "$@" >/dev/null
}

python="${PYTHON:-python3}"
venv=.venv
requirements=tests/python/requirements.txt
constraints=tests/python/constraints.txt

step "python"
if ! command -v "$python" >/dev/null 2>&1; then
    apt_install python3 python3-venv
fi
"$python" - <<'EOF'
import sys
if sys.version_info < (3, 11):
    sys.exit(f"Python 3.11 or newer is needed (the pinned numpy needs it); found {sys.version.split()[0]}: set PYTHON")
print(sys.executable, sys.version.split()[0])
EOF
# Debian and Ubuntu ship `venv` without `ensurepip` until python3-venv is installed.
if ! "$python" -c 'import ensurepip, venv' >/dev/null 2>&1; then
    apt_install python3-venv
fi

step "virtual environment ($venv)"
if [ -x "$venv/bin/python" ] && ! "$venv/bin/python" -c '' >/dev/null 2>&1; then
    rm -rf "$venv"  # made by a Python that is gone
fi
if [ ! -x "$venv/bin/python" ]; then
    "$python" -m venv "$venv"
fi
# Reinstall only when the pins change.
stamp="$venv/.esrp-requirements"
wanted="$(cat "$requirements" "$constraints" | sha256sum | cut -d' ' -f1)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$wanted" ]; then
    "$venv/bin/python" -m pip install --disable-pip-version-check --quiet -r "$requirements" -c "$constraints"
    echo "$wanted" >"$stamp"
fi
"$venv/bin/python" -m pip list --disable-pip-version-check --format=freeze | grep -iE '^(dm-env-rpc|grpcio|protobuf|numpy)=='

step "binaries"
# Without a GPU the server renders on Mesa's CPU renderer: llvmpipe through OpenGL (EGL), or
# lavapipe through Vulkan.
if ! ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1 || ! ldconfig -p | grep -q 'libvulkan.so.1' \
    || ! ls /usr/share/glvnd/egl_vendor.d/*mesa*.json >/dev/null 2>&1; then
    apt_install mesa-vulkan-drivers libvulkan1 libegl1 libegl-mesa0 libgl1-mesa-dri
fi
export NODEVICE_SELECT=1
cargo build --locked -p esrp-server -p esrp-dataset
target_dir="$(cargo metadata --format-version 1 --no-deps | "$venv/bin/python" -c 'import json, sys; print(json.load(sys.stdin)["target_directory"])')"
export ESRP_SERVER_BIN="$target_dir/debug/esrp-server"
export ESRP_DATASET_BIN="$target_dir/debug/esrp-dataset"

cd tests/python
step "ruff"
"../../$venv/bin/ruff" check .
"../../$venv/bin/ruff" format --check .

step "mypy"
"../../$venv/bin/mypy" .

step "pytest"
"../../$venv/bin/python" -m pytest "$@"
