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


class Checks:
    """The run's checks: each printed as it is made, the failures counted."""

    def __init__(self) -> None:
        self.failures = 0

    def __call__(self, ok: bool, what: str) -> None:
        self.failures += 0 if ok else 1
        print(f"{'ok  ' if ok else 'FAIL'} {what}", flush=True)


def eval_command(address: str, team: str, out: Path, *options: str) -> list[str]:
    """`esrp eval` of the random agent on the challenge split, as `team`, into `out`."""
    return [
        sys.executable,
        "-m",
        "esrp.cli",
        "eval",
        "--agent",
        "random",
        "--split",
        "challenge",
        "--no-progress",
        *options,
        "--server",
        address,
        "--token",
        f"{team}-secret",
        "--out",
        str(out),
        "--fresh",
    ]


def write_tokens(work: Path, teams: list[str]) -> Path:
    """The token file: an agent token per team and one organiser (admin)."""
    tokens = "".join(f'[[token]]\nname = "{t}"\nsecret = "{t}-secret"\nrole = "agent"\n\n' for t in teams)
    tokens += '[[token]]\nname = "organiser"\nsecret = "organiser-secret"\nrole = "admin"\n'
    path = work / "tokens.toml"
    path.write_text(tokens)
    return path


def run_every_team(address: str, work: Path, teams: list[str], in_flight: int, check: Checks) -> float:
    """Every team's `esrp eval` at once, as separate processes; checks that each exits 0 and returns
    the seconds they took together."""
    started = time.monotonic()
    evals = [
        subprocess.Popen(
            eval_command(address, t, work / f"{t}.own.jsonl", "--episodes-in-flight", str(in_flight)),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for t in teams
    ]
    codes = [p.wait() for p in evals]
    check(all(c == 0 for c in codes), f"{len(teams)} concurrent esrp eval runs exit 0 ({codes})")
    return time.monotonic() - started


def check_counted(records: Path, teams: list[str], scenes: int, seconds: float, check: Checks) -> None:
    """Each team has exactly one counted record per challenge scene; prints the steps per second."""
    for t in teams:
        path = records / f"{t}.jsonl"
        lines = [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []
        counted = sum(1 for r in lines if r.get("counted") and r.get("split") == "challenge")
        distinct = {r["scene_id"] for r in lines}
        check(
            counted == scenes and len(lines) == scenes and len(distinct) == scenes,
            f"{t}: {counted} counted records of {len(distinct)} distinct scenes (want {scenes})",
        )
    steps = sum(
        json.loads(line)["steps"] for t in teams for line in (records / f"{t}.jsonl").read_text().splitlines()
    )
    episodes = len(teams) * scenes
    rate = steps / seconds
    print(f"     {episodes} episodes, {steps} steps in {seconds:.1f} s ({rate:.0f} steps/s)", flush=True)


def check_second_run_refused(address: str, work: Path, team: str, check: Checks) -> None:
    """A second `esrp eval` by a team that has played is refused: already played."""
    again = subprocess.run(
        eval_command(address, team, work / "again.jsonl", "--limit", "3"),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        check=False,
    )
    check(
        again.returncode == 1 and again.stderr.count("already played") >= 1,
        "a second run of a token is refused: already played",
    )


def check_verify(address: str, records: Path, teams: list[str], check: Checks) -> None:
    """`esrp verify` of every team's records, with the organiser's token, agrees on every one."""
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
            address,
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
    seconds = time.monotonic() - started
    last = verify.stdout.strip().splitlines()[-1] if verify.stdout.strip() else verify.stderr.strip()
    check(verify.returncode == 0, f"esrp verify: {last} ({seconds:.1f} s)")


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
    server_args = [
        "--tokens",
        str(write_tokens(work, teams)),
        "--challenge-seed",
        "challenge-run-measurement-seed",
        "--challenge-scenes",
        str(args.scenes),
        "--minival-scenes",
        "0",
        "--records",
        str(records),
    ]
    check = Checks()
    with esrp.LocalServer(*server_args, binary=args.server_binary) as server:
        seconds = run_every_team(server.address, work, teams, args.episodes_in_flight, check)
        check_counted(records, teams, args.scenes, seconds, check)
        check_second_run_refused(server.address, work, teams[0], check)
        check_verify(server.address, records, teams, check)
    print(f"records in {records}" if args.keep else f"(work folder {work})")
    return 1 if check.failures else 0


if __name__ == "__main__":
    sys.exit(main())
