"""Generates the esrp.v1 gRPC/protobuf stubs of the Python package from proto/esrp/v1/esrp.proto.

The stubs are checked in under src/esrp/v1/ and never edited by hand: run this after changing the
proto, with the `stubs` extra's grpcio-tools and mypy-protobuf pinned by constraints-lerobot.txt
(grpcio-tools 1.80.1, whose gencode, protobuf 6.31.1, both protobuf 6 and 7 run;
the venv scripts/python-tests.sh makes for LeRobot, .venv-lerobot, has them):

    .venv-lerobot/bin/python clients/python/tools/generate_proto.py            # rewrite src/esrp/v1/
    .venv-lerobot/bin/python clients/python/tools/generate_proto.py --check    # fail if stale

protoc runs with `-I proto`, so the files are named `esrp/v1/esrp.proto` in the descriptor pool (as
on the server and in reflection) and the generated code imports `esrp.v1.esrp_pb2`, which is this
package's own `esrp.v1` subpackage: the files are used exactly as protoc writes them.
"""

from __future__ import annotations

import argparse
import difflib
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[1]
REPOSITORY = PACKAGE_ROOT.parents[1]
PROTO_ROOT = REPOSITORY / "proto"
PROTO_FILE = PROTO_ROOT / "esrp" / "v1" / "esrp.proto"
CHECKED_IN = PACKAGE_ROOT / "src" / "esrp" / "v1"

# What protoc writes for esrp.proto: messages, gRPC stubs and their mypy-protobuf type stubs.
GENERATED = ("esrp_pb2.py", "esrp_pb2.pyi", "esrp_pb2_grpc.py", "esrp_pb2_grpc.pyi")


def generate(out: Path) -> dict[str, str]:
    """Runs protoc into `out` and returns the generated files' text by name."""
    bin_dir = Path(sys.executable).parent
    plugins = {name: bin_dir / name for name in ("protoc-gen-mypy", "protoc-gen-mypy_grpc")}
    for path in plugins.values():
        if not path.is_file():
            raise SystemExit(
                f"{path} is missing: install the stubs extra in this Python ({sys.executable}): "
                "pip install './clients/python[stubs]' -c clients/python/constraints-lerobot.txt"
            )
    command = [
        sys.executable,
        "-m",
        "grpc_tools.protoc",
        f"-I{PROTO_ROOT}",
        f"--plugin=protoc-gen-mypy={plugins['protoc-gen-mypy']}",
        f"--plugin=protoc-gen-mypy_grpc={plugins['protoc-gen-mypy_grpc']}",
        f"--python_out={out}",
        f"--grpc_python_out={out}",
        f"--mypy_out={out}",
        f"--mypy_grpc_out={out}",
        str(PROTO_FILE),
    ]
    out.mkdir(parents=True, exist_ok=True)
    run = subprocess.run(command, capture_output=True, text=True)
    if run.returncode != 0:
        raise RuntimeError(f"protoc failed ({run.returncode}): {run.stderr}")
    folder = out / "esrp" / "v1"
    return {name: (folder / name).read_text() for name in GENERATED}


def stale_files(generated: dict[str, str], checked_in: Path = CHECKED_IN) -> dict[str, str]:
    """The checked-in files that differ from `generated`, each with a unified diff."""
    differences = {}
    for name, text in generated.items():
        path = checked_in / name
        current = path.read_text() if path.is_file() else ""
        if current != text:
            diff = difflib.unified_diff(
                current.splitlines(keepends=True),
                text.splitlines(keepends=True),
                f"checked-in {name}",
                f"generated {name}",
            )
            differences[name] = "".join(diff)
    return differences


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--check", action="store_true", help="only compare; exit 1 when stale")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        generated = generate(Path(folder))
        stale = stale_files(generated)
        if args.check:
            for name, diff in stale.items():
                print(f"{name} is stale:\n{diff[:4000]}")
            return 1 if stale else 0
        for name in GENERATED:
            shutil.copyfile(Path(folder, "esrp", "v1", name), CHECKED_IN / name)
    print(f"wrote {', '.join(GENERATED)} to {CHECKED_IN}" if stale else "already up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
