#!/usr/bin/env bash
# The main job: builds the simulator and replays the expert trajectory of the example scene,
# printing SR / OSR / RDR. (The gRPC server on the built-in benchmark replaces this demo when
# it lands: see issue "gRPC server (esrp-server)".) Usage: bash scripts/demo.sh
set -euo pipefail
cd "$(dirname "$0")/.."
cargo run --release --locked -q -p esrp-core --example replay -- server/core/examples/scenes/bedroom.json
echo
echo "The gRPC server (esrp-server) on the built-in benchmark is not built yet; this demo runs the simulator alone."
