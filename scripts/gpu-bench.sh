#!/usr/bin/env bash
# The server's throughput on the machine it runs on, every figure issue 40 asks for, in one run
# that builds nothing and keeps to a time budget (480 s by default): for a lent GPU machine,
# where the binaries are carried, and tested on this machine's lavapipe.
#
#   scripts/gpu-bench.sh --prepare [3.X]      # here: binaries, Python 3.X's packages (3.12) and the
#                                             # Vulkan loader in dist/gpu-bench, and dist/gpu-bench.tar.xz
#   scripts/gpu-bench.sh [--bin DIR] [--out DIR] [--budget SECONDS] [--seconds S] [--backend NAME]
#
# On a lent machine: carry dist/gpu-bench.tar.xz (~30 MB). The tree goes too and must stay under
# the carry limit (64 MiB): for that call, untrack and exclude the checkpoints (`git rm -r -q
# --cached docs/results/checkpoints; echo /docs/results/checkpoints >> .git/info/exclude`; after
# it, `git reset -q HEAD -- docs/results/checkpoints` and the exclude line removed). There:
#   tar -xJf dist/gpu-bench.tar.xz -C dist && bash scripts/gpu-bench.sh --budget 470 --out "$OUT"
#
# What it measures, in this order (what decides issue 40 first), each step only if the budget
# leaves room for it (a skipped step is said in the summary):
#   1. standard: esrp-bench's scenarios with the server's stage breakdown (--breakdown);
#   1b. compute: the compute rasteriser (--render-rasterizer compute): the renderer alone (views
#      bench), one server driven by 4 client processes, 8 servers driven by 8 and by 16;
#   2. scale-out at 8: 8 servers started first, driven by 8 client processes (one each) and by
#      16 (two each), against one server driven by the same 8 processes; then 8 servers whose
#      runtimes share the cores out (--worker-threads cores/8) driven by 8; then 8 servers
#      reached over their Unix domain sockets (--listen-unix) by 8 and by 16 processes;
#   3. pipeline: batches in flight per render thread (--render-pipeline 1, 2, 3), one server
#      driven by 4 client processes (so that the client is not the limit), with the breakdown
#      (on a GPU it says how busy the device kept drawing, by its timestamps); then the first
#      again with --render-timestamps off (what they cost), and with --render-depth-buffers
#      per-page (a depth buffer per view's pass), also measured on the renderer alone;
#   4. renderer: the renderer alone, no server (esrp-render's views bench, carried): batches of 1
#      to 256 views, 256 at 64 and 256 pixels, top-down, every plane; then 4 and 8 processes
#      rendering at once (what one device gives, whatever the server);
#   5. threads: render threads 1, 2 and 4, one server driven by 4 client processes;
#   6. scale-out at 2 and 4 servers, as in 2;
#   7. devices: render devices 2 and 4 (threads auto), 4 client processes;
#   8. episodes: batch-64 with 1 to 1,024 episodes (the curve of steps/s against episodes);
#   9. clients: stream-mux-64 driven by 1, 2, 4 and 8 client processes (is the client the limit?);
#  10. gl: whether --render-backend gl starts there (unary-1; a failure is said in the summary);
#  11. python: python -m esrp.bench's env-1 and vec-64 against the server (over TCP, then over
#      its Unix domain socket), then vec-64 spread over 4 and over 8 servers (--servers), where this
#      machine's python3 imports esrp (clients/python/src is put before any PYTHONPATH given, where
#      its dependencies, and esrp-native for the native transport, may be installed).
# Every step writes its esrp-bench JSON under OUT (default $OUT, else gpu-bench-out) and the
# machine's busy cores while it ran (cpu-NAME.txt: from /proc/stat, all processes), and
# OUT/summary.md gathers the tables (python3 scripts/gpu_bench_summary.py OUT).
set -euo pipefail
cd "$(dirname "$0")/.."

BIN=dist/gpu-bench
OUT_DIR=${OUT:-gpu-bench-out}
BUDGET=480
SECONDS_EACH=4
BACKEND=auto

usage() { sed -n '2,/^set -euo pipefail/{/^#/p}' "$0" | sed 's/^# \{0,1\}//'; }

if [[ "${1:-}" == "--prepare" ]]; then
    # The device builds nothing: the binaries, the Python side of its python3 (PYTHON, default
    # 3.12, the last lent machine's) and the Vulkan loader are made or fetched here, into BIN and
    # one archive to carry. PYTHON's wheels come from the package index at the pinned versions
    # (clients/python/constraints.txt), esrp-native is built here (maturin, from the venv or
    # PATH); all are unpacked into BIN/site, which the script puts on PYTHONPATH (no pip there).
    python_version=${2:-3.12}
    [[ "$python_version" =~ ^3\.[0-9]+$ ]] || { echo "gpu-bench.sh: --prepare [3.X]: a Python version" >&2; exit 2; }
    cargo build --release -p esrp-server -p esrp-client --features esrp-client/tools --bin esrp-server --bin esrp-bench
    # The renderer alone: esrp-render's `views` bench, carried as esrp-render-views.
    views=$(cargo bench --locked -p esrp-render --bench views --no-run --message-format=json \
        | grep -o '"executable":"[^"]*"' | tail -1 | cut -d'"' -f4)
    [[ -x "$views" ]] || { echo "gpu-bench.sh: cargo did not say where the views bench is" >&2; exit 1; }
    rm -rf "$BIN" && mkdir -p "$BIN"
    cp "$views" "$BIN/esrp-render-views"
    for binary in esrp-server esrp-bench; do
        cp "target/release/$binary" "$BIN/$binary"
    done
    strip "$BIN"/esrp-*
    work=$(mktemp -d)
    trap 'rm -rf "$work"' EXIT
    PATH="$PWD/.venv/bin:$PATH"
    python3 -m pip download --quiet --only-binary=:all: --no-deps --python-version "$python_version" \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        -c clients/python/constraints.txt -d "$work/wheels" \
        grpcio protobuf numpy gymnasium farama-notifications cloudpickle typing_extensions
    maturin build --quiet --release --manifest-path clients/python/native/Cargo.toml --out "$work/wheels"
    for wheel in "$work"/wheels/*.whl; do
        python3 -m zipfile -e "$wheel" "$BIN/site"
    done
    echo "$python_version" > "$BIN/site/PYTHON_VERSION"
    # The Vulkan loader: a GPU container may have NVIDIA's driver and ICD but not libvulkan.so.1.
    (cd "$work" && apt-get download libvulkan1 > /dev/null)
    dpkg-deb -x "$work"/libvulkan1_*.deb "$BIN/vulkan"
    tar -C "$(dirname "$BIN")" -cJf "$BIN.tar.xz" "$(basename "$BIN")"
    du -sh "$BIN" "$BIN.tar.xz"
    exit 0
fi

while [[ $# -gt 0 ]]; do
    case "$1" in
        --bin) BIN=$2; shift 2 ;;
        --out) OUT_DIR=$2; shift 2 ;;
        --budget) BUDGET=$2; shift 2 ;;
        --seconds) SECONDS_EACH=$2; shift 2 ;;
        --backend) BACKEND=$2; shift 2 ;;
        -h|--help) usage; exit 0 ;;
        *) echo "gpu-bench.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
    esac
done
for binary in esrp-server esrp-bench; do
    if [[ ! -x "$BIN/$binary" ]]; then
        echo "gpu-bench.sh: no $BIN/$binary: run scripts/gpu-bench.sh --prepare first (or give --bin DIR)" >&2
        exit 2
    fi
done
if ! [[ "$BUDGET" =~ ^[0-9]+$ && "$SECONDS_EACH" =~ ^[0-9]+([.][0-9]+)?$ ]]; then
    echo "gpu-bench.sh: --budget takes whole seconds and --seconds a number" >&2
    exit 2
fi
mkdir -p "$OUT_DIR"
export NODEVICE_SELECT=1 ESRP_LOG=${ESRP_LOG:-warn}
# What --prepare brought: its Python packages (for the python version it was made for), and the
# Vulkan loader where the machine has none; NVIDIA's ICD where the loader would not look for it.
if [[ -f "$BIN/site/PYTHON_VERSION" ]]; then
    if [[ "$(python3 -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2> /dev/null)" == "$(cat "$BIN/site/PYTHON_VERSION")" ]]; then
        export PYTHONPATH=$PWD/$BIN/site${PYTHONPATH:+:$PYTHONPATH}
    else
        echo "gpu-bench.sh: $BIN/site is for Python $(cat "$BIN/site/PYTHON_VERSION"), python3 here is another: not used" >&2
    fi
fi
vulkan_libs=$BIN/vulkan/usr/lib/x86_64-linux-gnu
if [[ -d $vulkan_libs ]] && ! ldconfig -p 2> /dev/null | grep -q 'libvulkan\.so\.1 '; then
    export LD_LIBRARY_PATH=$PWD/$vulkan_libs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
fi
nvidia_icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
if [[ -z ${VK_DRIVER_FILES:-} && -z ${VK_ICD_FILENAMES:-} && -f $nvidia_icd ]]; then
    export VK_DRIVER_FILES=$nvidia_icd
fi
# One scene cache for every server started here: the built-in benchmark's scenes are built once.
export ESRP_SCENE_CACHE=${ESRP_SCENE_CACHE:-$OUT_DIR/scene-cache}
START=$(date +%s)
SKIPPED=()

left() { echo $((BUDGET - ($(date +%s) - START))); }

# step NAME NEEDED_SECONDS: whether NAME may run (else it is recorded as skipped).
step() {
    if (( $(left) < $2 )); then
        SKIPPED+=("$1 (needs about $2 s, $(left) s left)")
        echo "== $1: skipped, $(left) s of the budget left" >&2
        return 1
    fi
    echo "== $1 ($(left) s of the budget left)" >&2
}

# The machine's CPU counters (all cores): busy and total jiffies.
cpu_counters() { awk '/^cpu /{busy = $2 + $3 + $4 + $7 + $8 + $9; print busy, busy + $5 + $6; exit}' /proc/stat; }
# measured NAME COMMAND...: runs COMMAND and writes the cores it kept busy on average to cpu-NAME.txt.
measured() {
    local name=$1 before after status=0
    shift
    before=$(cpu_counters)
    "$@" || status=$?
    after=$(cpu_counters)
    echo "$before $after $(nproc)" | awk '{t = $4 - $2; printf "%.1f\n", (t > 0 ? ($3 - $1) / t * $5 : 0)}' \
        > "$OUT_DIR/cpu-$name.txt"
    return "$status"
}

bench_on() { # bench_on BACKEND JSON SERVER_ARGS ARGS...: esrp-bench against a server it starts
    local backend=$1 json=$2 extra=$3; shift 3
    measured "${json%.json}" "$BIN/esrp-bench" --server-binary "$BIN/esrp-server" --seconds "$SECONDS_EACH" \
        --json "$OUT_DIR/$json" --server-args="--render-backend=$backend --no-generate-ahead${extra:+ $extra}" "$@" \
        >> "$OUT_DIR/bench.log" 2>&1
}
bench() { bench_on "$BACKEND" "$1" "" "${@:2}"; }  # bench JSON ARGS...: with the backend
bench_args() { bench_on "$BACKEND" "$@"; }          # bench_args JSON SERVER_ARGS ARGS...

{
    echo "date: $(date -u +%Y-%m-%dT%H:%M:%SZ)"
    echo "cpus: $(nproc)"
    grep -m1 'model name' /proc/cpuinfo | sed 's/.*: /cpu: /' || true
    command -v nvidia-smi > /dev/null && nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | sed 's/^/gpu: /' || true
    echo "server: $("$BIN/esrp-server" --version)"
    echo "backend: $BACKEND; seconds per scenario: $SECONDS_EACH; budget: $BUDGET s"
} > "$OUT_DIR/machine.txt"
cat "$OUT_DIR/machine.txt" >&2

# Scale-out: N servers started first (their start is not measured), the same client processes
# against them (process i drives server i modulo N) and against the first alone.
# The servers' process ids, one a line: start_server runs in a command substitution, a subshell
# whose variables do not come back.
SERVER_PIDS=$OUT_DIR/.server-pids
: > "$SERVER_PIDS"
start_server() { # start_server LOG [ARGS...]: a server on a free port, its address once it listens
    # (with --listen-unix among ARGS, its socket's: unix:PATH)
    # Its stdin is a `sleep` that outlives the script at worst by the budget: its stderr goes
    # nowhere, so that it holds no pipe of whoever reads this script's output (a `| tee` would
    # wait for it).
    local log=$1
    shift
    "$BIN/esrp-server" --listen 127.0.0.1:0 --render-backend "$BACKEND" --no-generate-ahead "$@" \
        --stop-on-stdin-close < <(exec sleep "$BUDGET" 2> /dev/null) > "$log" 2>&1 &
    echo "$!" >> "$SERVER_PIDS"
    local pattern='listening on [^ ]*'
    [[ " $* " == *" --listen-unix "* ]] && pattern='listening on unix:[^ ]*'
    for _ in $(seq 200); do
        grep -q "$pattern" "$log" 2> /dev/null && break
        sleep 0.1
    done
    local address
    address=$(grep -o "$pattern" "$log" | head -1 | awk '{print $3}')
    [[ $address == unix:* ]] && echo "$address" || echo "http://$address"
}
stop_servers() { # stops every server start_server started, and waits (10 s at most each) until it is gone
    local pid
    while read -r pid; do kill "$pid" 2> /dev/null || true; done < "$SERVER_PIDS"
    # Not this shell's children (their subshell has ended): `wait` cannot see them.
    while read -r pid; do
        for _ in $(seq 100); do
            kill -0 "$pid" 2> /dev/null || break
            sleep 0.1
        done
    done < "$SERVER_PIDS"
    : > "$SERVER_PIDS"
}
trap 'stop_servers; rm -f "$SERVER_PIDS"' EXIT
# start_servers N TAG [ARGS...]: N servers with ARGS (logs server-N-I[TAG].txt), their addresses in
# ADDRESSES and comma-separated in LIST, the scenes built on each by a first unmeasured pass. With
# TAG -unix, each also serves a Unix domain socket (in /tmp: a socket's path must be short) and
# ADDRESSES are the sockets.
start_servers() {
    local n=$1 tag=$2 i socket
    shift 2
    ADDRESSES=()
    for ((i = 0; i < n; i++)); do
        socket=()
        [[ $tag == -unix ]] && socket=(--listen-unix "/tmp/esrp-gpu-bench-$$-$i.sock")
        ADDRESSES+=("$(start_server "$OUT_DIR/server-$n-$i$tag.txt" "${socket[@]}" "$@")")
    done
    LIST=$(IFS=,; echo "${ADDRESSES[*]}")
    "$BIN/esrp-bench" --server "$LIST" --processes "$n" --scenarios stream-mux-64 --seconds 1 > /dev/null 2>&1 || true
}
scale_out() { # scale_out N: N servers against one, N client processes (and 2N against N servers at 8)
    local n=$1 target part
    start_servers "$n" ""
    for part in servers one; do
        target=$LIST
        [[ $part == one ]] && target=${ADDRESSES[0]}
        measured "$part-$n" "$BIN/esrp-bench" --server "$target" --processes "$n" \
            --scenarios stream-mux-64,batch-64 --seconds "$SECONDS_EACH" --json "$OUT_DIR/$part-$n.json" \
            >> "$OUT_DIR/bench.log" 2>&1 || true
    done
    if (( n == 8 )) && step "servers-8x2" 20; then
        measured "servers-8x2" "$BIN/esrp-bench" --server "$LIST" --processes 16 --scenarios stream-mux-64 \
            --seconds "$SECONDS_EACH" --json "$OUT_DIR/servers-8x2.json" >> "$OUT_DIR/bench.log" 2>&1 || true
    fi
    stop_servers
    # The same 8 servers with the cores shared out among their runtimes (by default each takes
    # the cores less one), driven by 8 processes.
    if (( n == 8 )) && step "servers-8-shared" 30; then
        local workers=$(( $(nproc) / n > 1 ? $(nproc) / n : 1 ))
        start_servers "$n" -shared --worker-threads "$workers"
        measured "servers-8-shared" "$BIN/esrp-bench" --server "$LIST" --processes "$n" --scenarios stream-mux-64 \
            --seconds "$SECONDS_EACH" --json "$OUT_DIR/servers-8-shared.json" >> "$OUT_DIR/bench.log" 2>&1 || true
        echo "$workers" > "$OUT_DIR/servers-8-shared-workers.txt"
        stop_servers
    fi
    # The same 8 servers and processes, the clients on their Unix domain sockets instead of TCP.
    if (( n == 8 )) && step "servers-8-unix" 35; then
        start_servers "$n" -unix
        measured "servers-8-unix" "$BIN/esrp-bench" --server "$LIST" --processes "$n" \
            --scenarios stream-mux-64,batch-64 --seconds "$SECONDS_EACH" --json "$OUT_DIR/servers-8-unix.json" \
            >> "$OUT_DIR/bench.log" 2>&1 || true
        measured "servers-8x2-unix" "$BIN/esrp-bench" --server "$LIST" --processes 16 --scenarios stream-mux-64 \
            --seconds "$SECONDS_EACH" --json "$OUT_DIR/servers-8x2-unix.json" >> "$OUT_DIR/bench.log" 2>&1 || true
        stop_servers
    fi
}

# The per-step costs below are what each step took on the 2-core VM, rounded up.
if step standard 60; then
    bench standard.json --breakdown \
        --scenarios unary-1,stream-1,stream-1-pipelined,unary-64,streams-64,stream-mux-64,batch-64
fi
# The compute rasteriser (--render-rasterizer compute: compute shaders instead of the graphics
# pipeline, whose fixed-function hardware an H100 or H200 has little of): the renderer alone, one
# server driven by 4 client processes (with the breakdown), 8 servers driven by 8 and by 16.
if [[ -x $BIN/esrp-render-views ]] && step renderer-compute 20; then
    ESRP_RENDER_RASTERIZER=compute ESRP_RENDER_BACKEND=$BACKEND ESRP_BENCH_SECONDS=1 ESRP_BENCH_CULL=on \
        ESRP_BENCH_CASES=ego-1,ego-64,ego-256,top-256,full-256 ESRP_BENCH_JSON=$OUT_DIR/renderer-compute.json \
        measured renderer-compute "$BIN/esrp-render-views" --bench >> "$OUT_DIR/renderer.log" 2>&1 \
        || SKIPPED+=("renderer-compute (the views bench failed: see renderer.log)")
fi
if step compute 30; then
    bench_args compute.json "--render-rasterizer=compute" --breakdown --scenarios stream-mux-64,batch-64 --processes 4 \
        || SKIPPED+=("compute (the compute rasteriser's server failed: see bench.log)")
fi
if step compute-servers-8 50; then
    start_servers 8 -compute --render-rasterizer compute
    measured compute-servers-8 "$BIN/esrp-bench" --server "$LIST" --processes 8 --scenarios stream-mux-64,batch-64 \
        --seconds "$SECONDS_EACH" --json "$OUT_DIR/compute-servers-8.json" >> "$OUT_DIR/bench.log" 2>&1 || true
    measured compute-servers-8x2 "$BIN/esrp-bench" --server "$LIST" --processes 16 --scenarios stream-mux-64 \
        --seconds "$SECONDS_EACH" --json "$OUT_DIR/compute-servers-8x2.json" >> "$OUT_DIR/bench.log" 2>&1 || true
    stop_servers
fi
if step servers-8 100; then
    scale_out 8
fi
for depth in 1 2 3; do
    if step "pipeline-$depth" 25; then
        bench_args "pipeline-$depth.json" "--render-pipeline=$depth" --breakdown \
            --scenarios stream-mux-64,batch-64 --processes 4
    fi
done
# What the device's timestamps cost (auto times a GPU): pipeline-1 again without them.
if step timestamps-off 25; then
    bench_args timestamps-off.json "--render-pipeline=1 --render-timestamps=off" --breakdown \
        --scenarios stream-mux-64,batch-64 --processes 4
fi
# A depth buffer per page (--render-depth-buffers per-page): a batch's passes no longer wait for
# each other's depth writes; pipeline-1 again with it, then the renderer alone with it.
if step depth-per-page 25; then
    bench_args depth-per-page.json "--render-pipeline=1 --render-depth-buffers=per-page" --breakdown \
        --scenarios stream-mux-64,batch-64 --processes 4
fi
if [[ -x $BIN/esrp-render-views ]] && step renderer-depth 15; then
    for depth in shared per-page; do
        ESRP_RENDER_DEPTH_BUFFERS=$depth ESRP_RENDER_BACKEND=$BACKEND ESRP_BENCH_SECONDS=1 ESRP_BENCH_CULL=on \
            ESRP_BENCH_CASES=ego-1,ego-64,ego-256,full-256 ESRP_BENCH_JSON=$OUT_DIR/renderer-depth-$depth.json \
            "$BIN/esrp-render-views" --bench >> "$OUT_DIR/renderer.log" 2>&1 \
            || SKIPPED+=("renderer-depth-$depth (the views bench failed: see renderer.log)")
    done
fi
# The renderer alone, no server (esrp-render's views bench): batches of 1 to 256 views, 256 at
# 64 and 256 pixels, top-down and with every plane; then several processes at once, each with
# a device of its own, measuring together (does the GPU, not one process, cap?).
if [[ -x $BIN/esrp-render-views ]]; then
    if step renderer 40; then
        ESRP_RENDER_BACKEND=$BACKEND ESRP_BENCH_SECONDS=1 ESRP_BENCH_JSON=$OUT_DIR/renderer.json \
            measured renderer "$BIN/esrp-render-views" --bench >> "$OUT_DIR/renderer.log" 2>&1 \
            || SKIPPED+=("renderer (the views bench failed: see renderer.log)")
    fi
    for n in 4 8; do
        if step "renderer-x$n" 15; then
            start_at=$(( $(date +%s) + 3 ))
            pids=()
            for ((i = 0; i < n; i++)); do
                ESRP_RENDER_BACKEND=$BACKEND ESRP_BENCH_SECONDS=2 ESRP_BENCH_CASES=ego-64,ego-256 ESRP_BENCH_CULL=on \
                    ESRP_BENCH_START_AT=$start_at ESRP_BENCH_JSON=$OUT_DIR/renderer-x$n-$i.json \
                    "$BIN/esrp-render-views" --bench >> "$OUT_DIR/renderer.log" 2>&1 &
                pids+=("$!")
            done
            measured "renderer-x$n" wait "${pids[@]}" || SKIPPED+=("renderer-x$n (a views bench failed: see renderer.log)")
        fi
    done
else
    SKIPPED+=("renderer ($BIN/esrp-render-views is missing: made by --prepare)")
fi
for threads in 1 2 4; do
    if step "threads-$threads" 25; then
        bench_args "threads-$threads.json" "--render-threads=$threads" --breakdown \
            --scenarios batch-64,stream-mux-64 --processes 4
    fi
done
for n in 2 4; do
    if step "servers-$n" $((30 + 5 * n)); then
        scale_out "$n"
    fi
done
for devices in 2 4; do
    if step "devices-$devices" 25; then
        bench_args "devices-$devices.json" "--render-devices=$devices" --breakdown \
            --scenarios batch-64,stream-mux-64 --processes 4
    fi
done
for episodes in 1 4 16 64 256 1024; do
    if step "episodes-$episodes" 15; then
        bench "episodes-$episodes.json" --scenarios batch-64 --episodes "$episodes"
    fi
done
for processes in 1 2 4 8; do
    if step "clients-$processes" 15; then
        bench "clients-$processes.json" --scenarios stream-mux-64 --processes "$processes"
    fi
done
if step gl 15; then
    if ! bench_on gl gl.json "" --scenarios unary-1; then
        rm -f "$OUT_DIR/gl.json"
        SKIPPED+=("gl (--render-backend gl did not start or failed here: see bench.log)")
    fi
fi

if step python 40; then
    python_path=clients/python/src${PYTHONPATH:+:$PYTHONPATH}
    if PYTHONPATH=$python_path python3 -c 'import esrp, grpc, numpy, gymnasium' 2> /dev/null; then
        address=$(start_server "$OUT_DIR/python-server.txt")
        PYTHONPATH=$python_path timeout 100 python3 -m esrp.bench --server "${address#http://}" \
            --scenarios env-1,vec-64 --seconds "$SECONDS_EACH" --json "$OUT_DIR/python.json" \
            >> "$OUT_DIR/bench.log" 2>&1 || SKIPPED+=("python (python -m esrp.bench failed: see bench.log)")
        stop_servers
        if step python-unix 25; then
            address=$(start_server "$OUT_DIR/python-server-unix.txt" --listen-unix "/tmp/esrp-gpu-bench-$$-py.sock")
            PYTHONPATH=$python_path timeout 100 python3 -m esrp.bench --server "$address" \
                --scenarios env-1,vec-64 --seconds "$SECONDS_EACH" --json "$OUT_DIR/python-unix.json" \
                >> "$OUT_DIR/bench.log" 2>&1 || SKIPPED+=("python-unix (python -m esrp.bench failed: see bench.log)")
            stop_servers
        fi
        # One vector env of 64 spread over 4, then 8 servers (each reached over its socket):
        # what one trainer process makes of a machine's servers.
        for n in 4 8; do
            if step "python-spread-$n" 30; then
                start_servers "$n" -unix
                PYTHONPATH=$python_path measured "python-spread-$n" timeout 100 python3 -m esrp.bench \
                    --server "$LIST" --scenarios vec-64 --seconds "$SECONDS_EACH" \
                    --json "$OUT_DIR/python-spread-$n.json" >> "$OUT_DIR/bench.log" 2>&1 \
                    || SKIPPED+=("python-spread-$n (python -m esrp.bench failed: see bench.log)")
                stop_servers
            fi
        done
    else
        SKIPPED+=("python (python3 here does not import esrp and its dependencies)")
    fi
fi

printf '%s\n' "${SKIPPED[@]}" > "$OUT_DIR/skipped.txt"
echo "took $(($(date +%s) - START)) s of $BUDGET" >> "$OUT_DIR/machine.txt"
if command -v python3 > /dev/null; then
    python3 scripts/gpu_bench_summary.py "$OUT_DIR" > "$OUT_DIR/summary.md"
    cat "$OUT_DIR/summary.md"
fi
