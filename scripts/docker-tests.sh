#!/usr/bin/env bash
# Tests docker/: the container images against a real Docker engine, the compose file and the
# Kubernetes manifests (offline, against pinned schemas). Builds, with no container registry:
#   - the base image esrp-base:bookworm from Debian's packages (docker/debootstrap-base.sh; built
#     once, then reused: `docker rmi esrp-base:bookworm` to refresh it),
#   - esrp-server:test (server.Dockerfile, target runtime-prebuilt, from the esrp-server that the
#     tests built) and esrp-eval:test (eval.Dockerfile, target eval-prebuilt, from esrp-eval and
#     wheels of the Python package and its pinned dependencies made on the host),
#   - the wheels of scripts/build-wheels.sh (--server-profile dev) and esrp-wheels:trixie and
#     esrp-wheels:python3.10 (wheels.Dockerfile: Debian 13's Python 3.13, and the host's Python
#     3.10 on Debian 12 when it has one; no Rust toolchain; the wheels installed with pip;
#     esrp-base:trixie is built like the bookworm base),
# then runs docker/tests with pytest in .venv-docker (pinned by docker/tests/constraints.txt).
# Installs docker.io, docker-compose and debootstrap when missing and starts dockerd when none
# runs (as root). ESRP_SERVER_BIN and ESRP_EVAL_BIN, when both are set, name the binaries to put
# in the images instead of the debug builds. Where the engine cannot start, the image tests are skipped with the reason and
# the offline checks still run. Usage: bash scripts/docker-tests.sh [PYTEST ARGS...]
set -euo pipefail
cd "$(dirname "$0")/.."

step() { printf '\n==> %s (%s)\n' "$*" "$(date -u +%H:%M:%S)"; }
seconds() { echo $(($(date +%s) - $1)); }
# docker build, its log shown only when it fails (the classic builder's deprecation notice too).
build() {
    local log
    log="$(mktemp)"
    if ! docker build "$@" >"$log" 2>&1; then
        cat "$log" >&2
        rm -f "$log"
        return 1
    fi
    rm -f "$log"
}
started=$(date +%s)

apt_install() {
    if [ "$(id -u)" = 0 ]; then apt_get="apt-get"; else apt_get="sudo apt-get"; fi
    export DEBIAN_FRONTEND=noninteractive
    $apt_get update -qq
    $apt_get install -y -qq "$@" >/dev/null
}

step "docker engine"
missing=()
command -v docker >/dev/null 2>&1 || missing+=(docker.io)
command -v dockerd >/dev/null 2>&1 || missing+=(docker.io)
command -v debootstrap >/dev/null 2>&1 || missing+=(debootstrap)
if ! command -v docker-compose >/dev/null 2>&1 && ! docker compose version >/dev/null 2>&1; then
    missing+=(docker-compose)
fi
if [ ${#missing[@]} -gt 0 ]; then
    apt_install $(printf '%s\n' "${missing[@]}" | sort -u)
fi
unavailable=""
if ! docker info >/dev/null 2>&1; then
    if [ "$(id -u)" = 0 ] && command -v dockerd >/dev/null 2>&1; then
        # Left running for later runs, like a system service.
        nohup dockerd >/tmp/esrp-dockerd.log 2>&1 &
        for _ in $(seq 60); do
            docker info >/dev/null 2>&1 && break
            sleep 0.5
        done
    fi
    if ! docker info >/dev/null 2>&1; then
        unavailable="dockerd is not running and could not be started ($(tail -n 1 /tmp/esrp-dockerd.log 2>/dev/null || echo 'not root'))"
    fi
fi
if [ -n "$unavailable" ]; then
    echo "SKIPPING the image tests: $unavailable"
else
    docker version --format 'client {{.Client.Version}}, engine {{.Server.Version}}'
fi

step "virtual environment (.venv-docker)"
venv=.venv-docker
python="${PYTHON:-python3}"
if [ -x "$venv/bin/python" ] && ! "$venv/bin/python" -c '' >/dev/null 2>&1; then
    rm -rf "$venv"
fi
if [ ! -x "$venv/bin/python" ]; then
    if ! "$python" -c 'import ensurepip, venv' >/dev/null 2>&1; then apt_install python3-venv; fi
    "$python" -m venv "$venv"
fi
stamp="$venv/.esrp-requirements"
wanted="$(cat docker/tests/requirements.txt docker/tests/constraints.txt | sha256sum | cut -d' ' -f1)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$wanted" ]; then
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r docker/tests/requirements.txt \
        -c docker/tests/constraints.txt
    echo "$wanted" >"$stamp"
fi

if [ -z "$unavailable" ]; then
    step "binaries"
    target_dir="$(cargo metadata --format-version 1 --no-deps | "$venv/bin/python" -c 'import json, sys; print(json.load(sys.stdin)["target_directory"])')"
    # The debug builds the tests made (or those named by ESRP_SERVER_BIN and ESRP_EVAL_BIN).
    if [ -z "${ESRP_SERVER_BIN:-}" ] || [ -z "${ESRP_EVAL_BIN:-}" ]; then
        # With the features `cargo test --workspace` resolves: nothing is compiled again after it.
        cargo build --locked --workspace --bins
        export ESRP_SERVER_BIN="$target_dir/debug/esrp-server" ESRP_EVAL_BIN="$target_dir/debug/esrp-eval"
    fi
    export ESRP_SERVER_BIN ESRP_EVAL_BIN
    echo "$ESRP_SERVER_BIN, $ESRP_EVAL_BIN"
    work="$target_dir/docker"
    mkdir -p "$work"
    version="$(cargo metadata --format-version 1 --no-deps | "$venv/bin/python" -c 'import json, sys; print(next(p["version"] for p in json.load(sys.stdin)["packages"] if p["name"] == "esrp-server"))')"

    # esrp-base:SUITE from Debian's packages, built once and then reused.
    base_image() {
        local t
        t=$(date +%s)
        if docker image inspect "esrp-base:$1" >/dev/null 2>&1; then
            echo "reusing esrp-base:$1, built $(docker image inspect --format '{{.Created}}' "esrp-base:$1")"
        else
            bash docker/debootstrap-base.sh "esrp-base:$1" "$1"
        fi
        echo "base image esrp-base:$1: $(seconds "$t") s"
    }
    # dependency_wheels DIR PYTHON_VERSION CONSTRAINTS REQUIREMENT: into DIR, the wheels of
    # REQUIREMENT's dependencies for CPython PYTHON_VERSION on x86_64 manylinux, pinned by
    # CONSTRAINTS, whatever the host's Python; our own wheels are found in DIR itself.
    dependency_wheels() {
        "$venv/bin/python" -m pip download --quiet --disable-pip-version-check --dest "$1" --find-links "$1" \
            --only-binary=:all: --python-version "$2" --implementation cp --abi "cp${2/./}" --abi abi3 \
            --abi none --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
            --platform manylinux2014_x86_64 -c "$3" "$4"
    }
    step "base image esrp-base:bookworm (debootstrap)"
    base_image bookworm

    step "server image esrp-server:test (target runtime-prebuilt)"
    t=$(date +%s)
    # A build context of the binary alone, its debug info stripped (the debug build is ~300 MB).
    rm -rf "$work/server-context" && mkdir -p "$work/server-context"
    strip --strip-debug -o "$work/server-context/esrp-server" "$ESRP_SERVER_BIN"
    build --network host -f docker/server.Dockerfile --target runtime-prebuilt \
        --build-arg BASE=esrp-base:bookworm --build-arg BINARY=esrp-server --build-arg VERSION="$version" \
        -t esrp-server:test "$work/server-context"
    echo "server image: $(seconds "$t") s, $(docker image inspect --format '{{.Size}}' esrp-server:test | awk '{printf "%.0f MB", $1 / 1e6}')"

    step "eval image esrp-eval:test (target eval-prebuilt)"
    t=$(date +%s)
    rm -rf "$work/eval-context" && mkdir -p "$work/eval-context/wheels"
    strip --strip-debug -o "$work/eval-context/esrp-eval" "$ESRP_EVAL_BIN"
    # Wheels for the image's Python (Debian bookworm: CPython 3.11, glibc 2.36), whatever the
    # host's Python: the package as built from this tree, and its dependencies as pinned.
    "$venv/bin/python" -m pip wheel --quiet --disable-pip-version-check --no-deps \
        --wheel-dir "$work/eval-context/wheels" ./clients/python
    dependency_wheels "$work/eval-context/wheels" 3.11 clients/python/constraints.txt 'esrp[gym,ray]'
    build --network host -f docker/eval.Dockerfile --target eval-prebuilt \
        --build-arg BASE=esrp-base:bookworm --build-arg WHEELS=wheels --build-arg EVAL_BINARY=esrp-eval \
        --build-arg VERSION="$version" -t esrp-eval:test "$work/eval-context"
    echo "eval image: $(seconds "$t") s, $(docker image inspect --format '{{.Size}}' esrp-eval:test | awk '{printf "%.0f MB", $1 / 1e6}')"
    step "wheels (scripts/build-wheels.sh --server-profile dev) and the images that install them"
    t=$(date +%s)
    # The server as in the tests (dependencies at opt-level 2, its own code not optimised): what is
    # tested is the packaging, and a release build of the server would add many minutes. esrp-native
    # is the release build scripts/python-tests.sh installed.
    bash scripts/build-wheels.sh --server-profile dev --out "$work/wheels"
    echo "wheels: $(seconds "$t") s"
    wheel_images=()
    # Each: TAG SUITE PYTHON CONSTRAINTS [PREFIX]. Debian 13's own Python 3.13 (the newest Python
    # Debian ships), and the oldest the package supports, 3.10, which no Debian release ships: the
    # host's build (as for the Python 3.10 run of scripts/python-tests.sh), copied onto Debian 12.
    variants=("trixie trixie 3.13 clients/python/constraints.txt")
    python310="$(bash scripts/python310.sh || true)"
    if [ -n "$python310" ]; then
        prefix="$("$python310" -c 'import sys; print(sys.base_prefix)')"
        case "$prefix" in
        / | /usr | /usr/local)
            # A system Python: its prefix is the whole system, not a folder to copy.
            echo "the Python 3.10 at $prefix is a system one: the wheels are tried on Debian's Python 3.13 only"
            ;;
        *) variants+=("python3.10 bookworm 3.10 clients/python/constraints-py310.txt $prefix") ;;
        esac
    else
        echo "no python3.10 here: the wheels are tried on Debian's Python 3.13 only (set PYTHON310)"
    fi
    for variant in "${variants[@]}"; do
        read -r tag suite python_version pins prefix <<<"$variant"
        step "wheels image esrp-wheels:$tag (Debian $suite, Python $python_version${prefix:+ from $prefix})"
        base_image "$suite"
        t=$(date +%s)
        context="$work/wheels-$tag"
        rm -rf "$context" && mkdir -p "$context/wheels" "$context/python"
        cp "$work"/wheels/*.whl "$context/wheels/"
        if [ -n "$prefix" ]; then
            cp -a "$prefix/." "$context/python/"
        fi
        # Our dependencies' wheels for the image's Python, as pinned (esrp-server and esrp-native
        # come from the folder: they are not on the package index).
        dependency_wheels "$context/wheels" "$python_version" "$pins" 'esrp[gym]'
        build --network host -f docker/wheels.Dockerfile --build-arg BASE="esrp-base:$suite" \
            --build-arg PYTHON_PREFIX="$prefix" -t "esrp-wheels:$tag" "$context"
        rm -rf "$context"
        echo "wheels image esrp-wheels:$tag: $(seconds "$t") s"
        wheel_images+=("esrp-wheels:$tag")
    done
    export ESRP_DOCKER_WHEELS_IMAGES="${wheel_images[*]}"
    # The images these builds replaced, and the classic builder's untagged stage images, would pile
    # up run after run: remove the untagged ones of ours (at the price of rebuilding the eval
    # image's venv stage next time, ~20 s).
    for title in esrp-server esrp-eval esrp-wheels; do
        docker image prune --force --filter "label=org.opencontainers.image.title=$title" >/dev/null
    done
    export ESRP_DOCKER_SERVER_IMAGE=esrp-server:test ESRP_DOCKER_EVAL_IMAGE=esrp-eval:test
else
    export ESRP_DOCKER_UNAVAILABLE="$unavailable"
fi

step "docker tests: ruff"
(cd docker/tests && "../../$venv/bin/ruff" check . && "../../$venv/bin/ruff" format --check .)

step "docker tests: pytest (docker/tests)"
(cd docker/tests && "../../$venv/bin/python" -m pytest -p no:cacheprovider "$@")
echo "docker tests: $(seconds "$started") s in all"
