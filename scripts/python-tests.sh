#!/usr/bin/env bash
# Runs the Python tests against the real esrp-server binary: the Python client package
# (clients/python: `pip install ./clients/python[test]`, then ruff, mypy, pyright, the import contracts
# (lint-imports) and its pytest suite) and
# the end-to-end tests of tests/python (dm_env_rpc's compliance suites and whole DmEnvAdaptor
# episodes). Creates .venv (gitignored) with the pinned packages of both, builds the binaries,
# installs the client package as built from this tree, then lints and tests each. Works on a fresh
# machine with a Rust toolchain; installs python3-venv (and the CPU Vulkan driver) if missing, and
# Debian's chromium for the browser test of `esrp report`'s HTML page (Playwright drives that
# browser; Playwright's own browser downloads are never used).
# Usage: bash scripts/python-tests.sh [PYTEST ARGS for tests/python...]
set -euo pipefail
cd "$(dirname "$0")/.."

step() { printf '\n==> %s (%s)\n' "$*" "$(date -u +%H:%M:%S)"; }

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
client=clients/python
client_constraints=$client/constraints.txt

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
pip() { "$venv/bin/python" -m pip --disable-pip-version-check --quiet "$@"; }
# Reinstall the dependencies only when the pins change. The client package builds with the pinned
# hatchling from the venv (no build isolation), so every package that runs is pinned.
stamp="$venv/.esrp-requirements"
wanted="$(cat "$requirements" "$constraints" "$client_constraints" "$client/pyproject.toml" | sha256sum | cut -d' ' -f1)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$wanted" ]; then
    pip install -r "$requirements" -c "$constraints"
    pip install hatchling maturin -c "$client_constraints"
    pip install --no-build-isolation "./$client[test,train,ray,sb3,torchrl,minari]" -c "$client_constraints"
    echo "$wanted" >"$stamp"
fi
# The package itself, as built from this tree, every time (a wheel: what `pip install` gives users).
pip install --no-build-isolation --no-deps --force-reinstall "./$client"
step "the native transport (esrp-native: $client/native, built with maturin)"
# Optional for users; here it is installed, so this suite runs the client's hot path through it
# (tests/test_native.py compares it with grpcio's), while the Python 3.10 run below goes through
# grpcio. maturin runs cargo, which it looks for beside itself and on PATH.
PATH="$PWD/$venv/bin:$PATH" pip install --no-build-isolation --no-deps --force-reinstall "./$client/native"
"$venv/bin/python" -m pip list --disable-pip-version-check --format=freeze \
    | grep -iE '^(esrp|esrp-native|esrp_native|dm-env-rpc|grpcio|protobuf|numpy|gymnasium)=='

step "chromium (the browser test of esrp report)"
if [ ! -x /usr/bin/chromium ]; then
    apt_install chromium
fi
/usr/bin/chromium --version 2>/dev/null || true  # its wrapper script warns about the machine on stderr

step "binaries"
# Without a GPU the server renders on Mesa's CPU renderer: llvmpipe through OpenGL (EGL), or
# lavapipe through Vulkan.
if ! ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1 || ! ldconfig -p | grep -q 'libvulkan.so.1' \
    || ! ls /usr/share/glvnd/egl_vendor.d/*mesa*.json >/dev/null 2>&1; then
    apt_install mesa-vulkan-drivers libvulkan1 libegl1 libegl-mesa0 libgl1-mesa-dri
fi
export NODEVICE_SELECT=1
# Every binary of the workspace (esrp-server, esrp-dataset, and the Rust esrp-eval: the Python
# tests check that both evaluation tools read each other's results), with the features
# `cargo test --workspace` resolves, so that after the Rust tests nothing is compiled again.
cargo build --locked --workspace --bins
target_dir="$(cargo metadata --format-version 1 --no-deps | "$venv/bin/python" -c 'import json, sys; print(json.load(sys.stdin)["target_directory"])')"
export ESRP_SERVER_BIN="$target_dir/debug/esrp-server"
export ESRP_DATASET_BIN="$target_dir/debug/esrp-dataset"
export ESRP_EVAL_BIN="$target_dir/debug/esrp-eval"
export ESRP_CHROMIUM=/usr/bin/chromium

step "python client: ruff ($client)"
(cd "$client" && "../../$venv/bin/ruff" check . && "../../$venv/bin/ruff" format --check .)

step "python client: mypy (strict)"
(cd "$client" && "../../$venv/bin/mypy")

step "python client: pyright (src/, as users' editors check the package)"
# Pinned here; installed from npm beside the venv (pyright is a Node program, with no dependencies
# of its own), with Debian's Node.js where the machine has none.
pyright_version=1.1.414
pyright_dir="$venv/pyright-$pyright_version"
if [ ! -x "$pyright_dir/node_modules/.bin/pyright" ]; then
    if ! command -v npm >/dev/null 2>&1; then
        apt_install nodejs npm
    fi
    npm install --silent --no-audit --no-fund --prefix "$pyright_dir" "pyright@$pyright_version"
fi
(cd "$client" && "../../$pyright_dir/node_modules/.bin/pyright" --pythonpath "../../$venv/bin/python")

step "python client: import contracts (lint-imports; $client/pyproject.toml's [tool.importlinter])"
(cd "$client" && "../../$venv/bin/lint-imports")

step "python client: pytest (the installed package against the real server)"
# The package has a src/ layout, so `import esrp` in the tests is the installed wheel.
(cd "$client" && "../../$venv/bin/python" -m pytest -p no:cacheprovider tests)

# The oldest Python the package supports (requires-python >= 3.10) gets the client's suite too,
# with its own pins (numpy 2.2 is the last for 3.10), when this machine has one.
python310="$(bash scripts/python310.sh || true)"
if [ -n "$python310" ]; then
    step "python client on $("$python310" --version) (.venv-py310)"
    if [ ! -x .venv-py310/bin/python ] || ! .venv-py310/bin/python -c '' >/dev/null 2>&1; then
        rm -rf .venv-py310
        "$python310" -m venv .venv-py310
    fi
    pip310() { .venv-py310/bin/python -m pip --disable-pip-version-check --quiet "$@"; }
    pip310 install hatchling -c "$client/constraints-py310.txt"
    pip310 install --no-build-isolation "./$client[test]" -c "$client/constraints-py310.txt"
    pip310 install --no-build-isolation --no-deps --force-reinstall "./$client"
    # Without the train and ray extras there: their tests skip themselves (pytest.importorskip).
    (cd "$client" && ../../.venv-py310/bin/python -m pytest -p no:cacheprovider -q tests)
else
    step "python client on Python 3.10: skipped (no python3.10 here; set PYTHON310 to test the oldest supported Python)"
fi

# LeRobot 0.4 pins torch < 2.11 and (through wandb) protobuf < 7: its export's tests run in a venv of
# their own, which also holds the package's oldest protobuf (6.32.1), so the client's core tests
# (calls, errors, streams, the envs) run there too, and the stub generator (grpcio-tools 1.80.1:
# test_stubs.py). The tests fail there, rather than skip, when it lacks LeRobot or the generator.
step "python client with LeRobot and protobuf 6 (.venv-lerobot)"
if [ ! -x .venv-lerobot/bin/python ] || ! .venv-lerobot/bin/python -c '' >/dev/null 2>&1; then
    rm -rf .venv-lerobot
    "$python" -m venv .venv-lerobot
fi
piplr() { .venv-lerobot/bin/python -m pip --disable-pip-version-check --quiet "$@"; }
stamp=.venv-lerobot/.esrp-requirements
wanted="$(cat "$client/constraints-lerobot.txt" "$client/pyproject.toml" | sha256sum | cut -d' ' -f1)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$wanted" ]; then
    # LeRobot's pynput needs evdev on Linux, published as source only: it is compiled here, with the
    # pinned setuptools (the venv's own is too old for its pyproject.toml) and Python's headers.
    if ! .venv-lerobot/bin/python -c 'import os, sysconfig; os.stat(os.path.join(sysconfig.get_paths()["include"], "Python.h"))' 2>/dev/null; then
        apt_install python3-dev
    fi
    piplr install hatchling setuptools -c "$client/constraints-lerobot.txt"
    piplr install --no-build-isolation "./$client[lerobot,stubs]" pytest -c "$client/constraints-lerobot.txt"
    echo "$wanted" >"$stamp"
fi
piplr install --no-build-isolation --no-deps --force-reinstall "./$client"
.venv-lerobot/bin/python -m pip list --disable-pip-version-check --format=freeze \
    | grep -iE '^(esrp|lerobot|torch|protobuf|grpcio|grpcio-tools)=='
(cd "$client" && ESRP_TESTS_REQUIRE=lerobot,torch,grpc_tools ../../.venv-lerobot/bin/python -m pytest \
    -p no:cacheprovider -q tests/test_lerobot.py tests/test_stubs.py tests/test_client.py tests/test_async.py \
    tests/test_errors.py tests/test_stream.py tests/test_gym.py tests/test_vector.py)

cd tests/python
step "dm_env_rpc tests: ruff"
"../../$venv/bin/ruff" check .
"../../$venv/bin/ruff" format --check .

step "dm_env_rpc tests: mypy"
"../../$venv/bin/mypy" .

step "dm_env_rpc tests: pytest"
"../../$venv/bin/python" -m pytest "$@"
