"""Measures the claim rule with a stock gRPC client: in each run, a fresh esrp-server (so that its
scenes are not built yet) gets `--creates` CreateEpisode calls from the plain grpcio stubs the
package ships (no cancellation-safe wrapper), each abandoned at a 20 ms deadline, half at 128 px
and half at 512 px with every sensor (an answer that arrives in time but exceeds grpcio's default
4 MB receive limit is dropped by the client too, and counted as abandoned). It prints, per run,
how many calls were abandoned, how many episodes were live a second after (the creates answered
in time: this client holds their ids but never names them again, so the server cannot tell them
from abandoned ones) and how many are live once the claim timeout (plus the reaper's tick) has
passed; the last must be 0 in every run.

    ESRP_SERVER_BIN=target/release/esrp-server python clients/python/tools/abandoned_creates.py --runs 10
"""

from __future__ import annotations

import argparse
import sys
import time

import grpc

import esrp
from esrp.v1 import esrp_pb2 as pb
from esrp.v1 import esrp_pb2_grpc as pb_grpc


def live(stub: pb_grpc.EsrpStub) -> int:
    return stub.ServerInfo(pb.ServerInfoRequest(), timeout=10).live_episodes


def one_run(run: int, creates: int, claim: int) -> tuple[int, int, int]:
    """Abandoned calls, live episodes just after, live episodes after the claim timeout."""
    args = ("--claim-timeout-seconds", str(claim), "--idle-timeout-seconds", "0")
    with esrp.LocalServer(*args) as server, grpc.insecure_channel(server.address) as channel:
        stub = pb_grpc.EsrpStub(channel)
        scenes = [
            s.id for s in stub.ListScenes(pb.ListScenesRequest(split=pb.SPLIT_TRAIN, page_size=1000)).scenes
        ]
        sensors = [
            pb.Sensors(resolution=128),
            pb.Sensors(resolution=512, ego_depth=True, ego_segmentation=True, current_top_down=True),
        ]
        abandoned = 0
        # Different unbuilt scenes in every run.
        start = (run * creates) % max(1, len(scenes) - creates)
        for index, scene in enumerate(scenes[start : start + creates]):
            try:
                stub.CreateEpisode(
                    pb.CreateEpisodeRequest(scene_id=scene, sensors=sensors[index % 2]), timeout=0.02
                )
            except grpc.RpcError as error:
                # An answer over grpcio's default 4 MB receive limit (512 px with every sensor) is
                # dropped by the client just the same: it never learns the id either.
                if error.code() in (
                    grpc.StatusCode.DEADLINE_EXCEEDED,
                    grpc.StatusCode.CANCELLED,
                    grpc.StatusCode.RESOURCE_EXHAUSTED,
                ):
                    abandoned += 1
                else:
                    raise
        time.sleep(1.0)
        right_after = live(stub)
        deadline = time.monotonic() + claim + 15
        left = live(stub)
        while left and time.monotonic() < deadline:
            time.sleep(0.25)
            left = live(stub)
        return abandoned, right_after, left


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--creates", type=int, default=20, help="creates per run (default 20)")
    parser.add_argument(
        "--claim", type=int, default=5, help="the servers' --claim-timeout-seconds (default 5)"
    )
    args = parser.parse_args()
    print("| run | abandoned | live 1 s after | live after the claim timeout |")
    print("|---:|---:|---:|---:|")
    clean = 0
    for run in range(args.runs):
        abandoned, after, left = one_run(run, args.creates, args.claim)
        clean += left == 0
        print(f"| {run + 1} | {abandoned} of {args.creates} | {after} | {left} |", flush=True)
    print(f"\n{clean} of {args.runs} runs left no episode")
    return 0 if clean == args.runs else 1


if __name__ == "__main__":
    sys.exit(main())
