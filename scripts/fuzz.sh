#!/usr/bin/env bash
# Coverage-guided fuzzing (cargo fuzz, libFuzzer) of ESRP's untrusted inputs, for a fixed time
# per target: a benchmark-like run, not part of scripts/test.sh. Installs cargo-fuzz and the
# nightly toolchain if missing. Usage: bash scripts/fuzz.sh [SECONDS per target, default 600]
#
# Each target keeps its growing corpus in fuzz/corpus/TARGET (not committed) and reads the
# committed seeds in fuzz/seeds/TARGET. A crash leaves its input in fuzz/artifacts/TARGET and
# fails the script: turn that input into a regression test in esrp-core's suite, fix the cause,
# and record the run in fuzz/README.md.
set -euo pipefail
cd "$(dirname "$0")/../fuzz"

seconds="${1:-600}"
targets=(scene_json esrp_v1_requests dm_env_requests)

if ! rustup toolchain list | grep -q '^nightly'; then
    rustup toolchain install nightly --profile minimal
fi
if ! cargo fuzz --version >/dev/null 2>&1; then
    cargo install cargo-fuzz --locked
fi

for target in "${targets[@]}"; do
    printf '\n==> %s for %s s\n' "$target" "$seconds"
    mkdir -p "corpus/$target"
    dict=()
    if [ -f "$target.dict" ]; then dict=("-dict=$target.dict"); fi
    # One job on one core; -max_len fits the seed scenes (up to ~20 KB); -timeout flags inputs
    # that take over 10 s (a hang). The summary lines (#runs, cov, ft, corp) end the log.
    cargo +nightly fuzz run --release "$target" "corpus/$target" "seeds/$target" -- \
        -max_total_time="$seconds" -max_len=65536 -timeout=10 -print_final_stats=1 "${dict[@]}"
done
