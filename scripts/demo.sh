#!/usr/bin/env bash
# The main job, until the gRPC server lands: generates the first scenes of the built-in
# benchmark esrp-bench-v1, validates them, and replays their expert trajectories through the
# simulator, printing SR / OSR / RDR. Usage: bash scripts/demo.sh [SCENES]
set -euo pipefail
cd "$(dirname "$0")/.."
scenes="${1:-24}"
out=target/demo/esrp-bench-v1
cargo build --release --locked -q -p esrp-dataset -p esrp-core --example replay
./target/release/esrp-dataset generate --out "$out" --scenes "$scenes" --force
./target/release/esrp-dataset validate "$out"
./target/release/examples/replay "$out"/scenes/*.json | tail -n 4
echo
echo "The gRPC server (esrp-server) is not built yet: this demo drives the simulator directly."
