"""Measures what watching an episode in the web viewer costs its agent: `esrp-bench --scenarios
unary-1` (one episode, one step at a time) against one server with the viewer on, alternately with
no watcher and with N watchers of the bench's episode (each reading the episode's event stream as
fast as frames come), R rounds. Prints the steps/s of every run and the ratio of the means.

    python clients/python/tools/viewer_watchers.py --server-binary target/release/esrp-server \\
        --bench-binary target/release/esrp-bench --watchers 20 --rounds 3
"""

from __future__ import annotations

import argparse
import http.client
import json
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from urllib.parse import urlsplit

import esrp


def episodes(viewer: str) -> list[dict[str, object]]:
    with urllib.request.urlopen(viewer + "api/episodes", timeout=10) as response:
        result: list[dict[str, object]] = json.loads(response.read())
        return result


def watch(viewer: str, episode: str, stop: threading.Event, frames: list[int], index: int) -> None:
    """Reads the episode's event stream until `stop`, counting frames."""
    url = urlsplit(viewer)
    connection = http.client.HTTPConnection(url.hostname or "127.0.0.1", url.port, timeout=30)
    connection.request("GET", f"/api/episodes/{episode}/watch")
    response = connection.getresponse()
    try:
        while not stop.is_set():
            chunk = response.read1(65536)
            if not chunk:
                break
            frames[index] += chunk.count(b"event: frame")
    except (http.client.HTTPException, OSError, ValueError):
        pass  # the stream ended with the bench's episode
    finally:
        connection.close()


def one_run(bench: str, server: esrp.LocalServer, watchers: int, seconds: float) -> tuple[float, int]:
    """unary-1's steps/s with `watchers` watching its episode, and the frames they got."""
    assert server.viewer_url is not None
    viewer = server.viewer_url
    before = {str(e["id"]) for e in episodes(viewer)}
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "bench.json"
        command = [bench, "--server", f"http://{server.address}", "--scenarios", "unary-1"]
        run = subprocess.Popen(
            [*command, "--seconds", str(seconds), "--json", str(out)], stdout=subprocess.DEVNULL
        )
        stop = threading.Event()
        frames = [0] * watchers
        threads: list[threading.Thread] = []
        if watchers:
            deadline = time.monotonic() + 60
            new: list[str] = []
            while not new and time.monotonic() < deadline and run.poll() is None:
                new = [str(e["id"]) for e in episodes(viewer) if str(e["id"]) not in before]
                time.sleep(0.02)
            if not new:
                raise SystemExit("the bench's episode never appeared in the viewer's list")
            for i in range(watchers):
                thread = threading.Thread(target=watch, args=(viewer, new[0], stop, frames, i), daemon=True)
                thread.start()
                threads.append(thread)
        code = run.wait()
        stop.set()
        if code != 0:
            raise SystemExit(f"esrp-bench exited with {code}")
        result = json.loads(out.read_text())["results"][0]
        return float(result["steps_per_second"]), sum(frames)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--server-binary", default=None)
    parser.add_argument("--bench-binary", default="target/release/esrp-bench")
    parser.add_argument("--watchers", type=int, default=20)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    with esrp.LocalServer("--http-listen", "127.0.0.1:0", binary=args.server_binary) as server:
        rows = {0: [], args.watchers: []}  # type: dict[int, list[float]]
        print("| round | watchers | unary-1 steps/s | frames the watchers got |")
        print("|---:|---:|---:|---:|")
        for r in range(args.rounds):
            for watchers in (0, args.watchers):
                rate, frames = one_run(args.bench_binary, server, watchers, args.seconds)
                rows[watchers].append(rate)
                print(f"| {r + 1} | {watchers} | {rate:,.0f} | {frames:,} |", flush=True)
        off = sum(rows[0]) / len(rows[0])
        on = sum(rows[args.watchers]) / len(rows[args.watchers])
        print(
            f"\nmean without watchers {off:,.0f} steps/s, with {args.watchers}: {on:,.0f} ({on / off:.2f}x)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
