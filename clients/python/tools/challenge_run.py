"""The challenge's goals, measured end to end on one server.

N agent tokens each run `esrp eval` (the random agent, as separate processes, concurrently) over an
S-scene challenge; each token must end with exactly S counted records in the server's records
folder, a second run of any token must be refused scene by scene, and `esrp verify` of all N x S
records with an admin token must agree on every one. Prints one line per check and the times;
exit status 0 when every check holds.

    .venv/bin/python clients/python/tools/challenge_run.py --server-binary target/release/esrp-server \
        --tokens 8 --scenes 200

Needs the `esrp` package (`pip install ./clients/python`) in the Python that runs it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import esrp


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--server-binary", default=None, help="esrp-server to start (default: as LocalServer finds it)"
    )
    parser.add_argument(
        "--tokens", type=int, default=8, help="agent tokens, each running esrp eval (default 8)"
    )
    parser.add_argument("--scenes", type=int, default=200, help="challenge scenes (default 200)")
    parser.add_argument("--episodes-in-flight", type=int, default=8, help="per esrp eval (default 8)")
    parser.add_argument("--keep", type=Path, default=None, help="keep the records in this folder")
    args = parser.parse_args()
    if args.tokens < 1 or args.scenes < 1:
        parser.error("--tokens and --scenes must be at least 1")

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="esrp-challenge-"))
    work.mkdir(parents=True, exist_ok=True)
    records = work / "records"
    teams = [f"team-{i:02d}" for i in range(1, args.tokens + 1)]
    tokens = "".join(f'[[token]]\nname = "{t}"\nsecret = "{t}-secret"\nrole = "agent"\n\n' for t in teams)
    tokens += '[[token]]\nname = "organiser"\nsecret = "organiser-secret"\nrole = "admin"\n'
    (work / "tokens.toml").write_text(tokens)
    server_args = [
        "--tokens",
        str(work / "tokens.toml"),
        "--challenge-seed",
        "challenge-run-measurement-seed",
        "--challenge-scenes",
        str(args.scenes),
        "--minival-scenes",
        "0",
        "--records",
        str(records),
    ]
    failures = 0

    def check(ok: bool, what: str) -> None:
        nonlocal failures
        failures += 0 if ok else 1
        print(f"{'ok  ' if ok else 'FAIL'} {what}", flush=True)

    with esrp.LocalServer(*server_args, binary=args.server_binary) as server:
        started = time.monotonic()
        evals = [
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "esrp.cli",
                    "eval",
                    "--agent",
                    "random",
                    "--split",
                    "challenge",
                    "--no-progress",
                    "--server",
                    server.address,
                    "--token",
                    f"{t}-secret",
                    "--episodes-in-flight",
                    str(args.episodes_in_flight),
                    "--out",
                    str(work / f"{t}.own.jsonl"),
                    "--fresh",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                text=True,
            )
            for t in teams
        ]
        codes = [p.wait() for p in evals]
        run_seconds = time.monotonic() - started
        check(all(c == 0 for c in codes), f"{args.tokens} concurrent esrp eval runs exit 0 ({codes})")
        counted = {}
        for t in teams:
            path = records / f"{t}.jsonl"
            lines = [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []
            counted[t] = sum(1 for r in lines if r.get("counted") and r.get("split") == "challenge")
            scenes = {r["scene_id"] for r in lines}
            check(
                counted[t] == args.scenes and len(lines) == args.scenes and len(scenes) == args.scenes,
                f"{t}: {counted[t]} counted records of {len(scenes)} distinct scenes (want {args.scenes})",
            )
        steps = sum(
            json.loads(line)["steps"]
            for t in teams
            for line in (records / f"{t}.jsonl").read_text().splitlines()
        )
        print(
            f"     {args.tokens * args.scenes} episodes, {steps} steps in {run_seconds:.1f} s "
            f"({steps / run_seconds:.0f} steps/s)",
            flush=True,
        )

        again = subprocess.run(
            [
                sys.executable,
                "-m",
                "esrp.cli",
                "eval",
                "--agent",
                "random",
                "--split",
                "challenge",
                "--no-progress",
                "--limit",
                "3",
                "--server",
                server.address,
                "--token",
                f"{teams[0]}-secret",
                "--out",
                str(work / "again.jsonl"),
                "--fresh",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            check=False,
        )
        check(
            again.returncode == 1 and again.stderr.count("already played") >= 1,
            "a second run of a token is refused: already played",
        )

        started = time.monotonic()
        files = [str(records / f"{t}.jsonl") for t in teams]
        verify = subprocess.run(
            [
                sys.executable,
                "-m",
                "esrp.cli",
                "verify",
                *files,
                "--server",
                server.address,
                "--token",
                "organiser-secret",
                "--no-progress",
                "--episodes-in-flight",
                "16",
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        verify_seconds = time.monotonic() - started
        last = verify.stdout.strip().splitlines()[-1] if verify.stdout.strip() else verify.stderr.strip()
        check(verify.returncode == 0, f"esrp verify: {last} ({verify_seconds:.1f} s)")
    print(f"records in {records}" if args.keep else f"(work folder {work})")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
