#!/usr/bin/env bash
# Builds the three wheels a Python user installs, into dist/ (or --out DIR), replacing older ones:
#   esrp         the Python package (pure Python, py3-none-any; hatchling)
#   esrp-native  the optional native transport (one abi3 wheel for every CPython >= 3.10; maturin)
#   esrp-server  the server binary (py3-none, maturin's `bin` bindings), which `esrp.LocalServer`
#                finds after ESRP_SERVER_BIN
# and shows with `auditwheel show` which manylinux policy each binary wheel meets (maturin tags
# them by the same audit: the glibc symbol versions they use). Then, on any Linux x86_64 machine
# with glibc at least as new, without a Rust toolchain:
#   pip install dist/*.whl            # or: pip install --find-links dist 'esrp[gym,server]' esrp-native
# Needs cargo (Rust >= 1.88) and Python >= 3.10 with venv; the build tools go into .venv-wheels,
# pinned by clients/python/constraints-wheels.txt.
# Usage: bash scripts/build-wheels.sh [--out DIR] [--server-profile release|dev]
#   --server-profile dev builds the server with cargo's dev profile (its dependencies optimised,
#   its own code not; for tests: it reuses more of a debug build). esrp-native is always release.
set -euo pipefail
cd "$(dirname "$0")/.."

out=dist
server_profile=release
while [ $# -gt 0 ]; do
    case "$1" in
    --out) out="${2:?--out needs a folder}"; shift 2 ;;
    --server-profile) server_profile="${2:?--server-profile needs release or dev}"; shift 2 ;;
    -h | --help) sed -n '2,17p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "build-wheels.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
    esac
done
case "$server_profile" in
release | dev) ;;
*) echo "build-wheels.sh: --server-profile must be release or dev, not $server_profile" >&2; exit 2 ;;
esac
command -v cargo >/dev/null 2>&1 || { echo "build-wheels.sh: cargo not found (install Rust >= 1.88)" >&2; exit 1; }
step() { printf '\n==> %s (%s)\n' "$*" "$(date -u +%H:%M:%S)"; }

step "build tools (.venv-wheels)"
venv=.venv-wheels
python="${PYTHON:-python3}"
if [ -x "$venv/bin/python" ] && ! "$venv/bin/python" -c '' >/dev/null 2>&1; then rm -rf "$venv"; fi
[ -x "$venv/bin/python" ] || "$python" -m venv "$venv"
stamp="$venv/.esrp-requirements"
wanted="$(sha256sum clients/python/constraints-wheels.txt | cut -d' ' -f1)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$wanted" ]; then
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check maturin hatchling auditwheel \
        -c clients/python/constraints-wheels.txt
    echo "$wanted" >"$stamp"
fi
mkdir -p "$out"
rm -f "$out"/esrp-*.whl "$out"/esrp_native-*.whl "$out"/esrp_server-*.whl
maturin() { "$venv/bin/maturin" "$@"; }

step "esrp (clients/python)"
"$venv/bin/python" -m pip wheel --quiet --disable-pip-version-check --no-deps --no-build-isolation \
    --wheel-dir "$out" ./clients/python

step "esrp-native (clients/python/native, release)"
maturin build --quiet --release -m clients/python/native/Cargo.toml --out "$out"

step "esrp-server (server/service, $server_profile)"
maturin build --quiet --profile "$server_profile" -m server/service/Cargo.toml --out "$out"

step "manylinux compliance (auditwheel show)"
for wheel in "$out"/esrp_native-*.whl "$out"/esrp_server-*.whl; do
    "$venv/bin/auditwheel" show "$wheel"
done

step "wheels in $out"
ls -l "$out"/esrp-*.whl "$out"/esrp_native-*.whl "$out"/esrp_server-*.whl
