"""A challenge from end to end, against the real server: participants' `esrp eval` runs on the
hidden split with agent tokens, the server's own records of them, `esrp verify` of those records
with an admin token, and the leaderboard built from the records folder."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

import esrp
from esrp.cli import main

TOKENS = """
[[token]]
name = "team-red"
secret = "red-secret"
role = "agent"

[[token]]
name = "team-blue"
secret = "blue-secret"
role = "agent"

[[token]]
name = "organiser"
secret = "organiser-secret"
role = "admin"
"""

SCENES = 3


@pytest.fixture(scope="module")
def challenge(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[esrp.LocalServer, Path]]:
    """A server with agent tokens, a 3-scene challenge and records; its records folder."""
    root = tmp_path_factory.mktemp("challenge")
    (root / "tokens.toml").write_text(TOKENS)
    records = root / "records"
    args = [
        "--tokens",
        str(root / "tokens.toml"),
        "--challenge-seed",
        "the-organisers-secret-seed",
        "--challenge-scenes",
        str(SCENES),
        "--minival-scenes",
        "1",
        "--records",
        str(records),
    ]
    with esrp.LocalServer(*args) as server:
        yield server, records


def test_participants_runs_are_recorded_verified_and_ranked(
    challenge: tuple[esrp.LocalServer, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    server, records = challenge
    with esrp.Client(server.address, token="red-secret") as red:
        info = red.server_info()
        assert (info.caller, info.role, info.challenge, info.recording) == (
            "team-red",
            "agent",
            True,
            "challenge",
        )
        hidden = list(red.scenes("challenge"))
        assert [s.id for s in hidden] == [f"challenge/{i:05d}" for i in range(SCENES)]
        with pytest.raises(esrp.PermissionDenied, match="role agent"):
            red.create_episode(hidden[0].id, privileged=True)
        # The goal image comes without its frame on the floor (the room's size in metres) until
        # the episode ends.
        with red.create_episode("minival/00000") as practice:
            assert practice.goal().frame is None
            while not practice.step(esrp.Action.LEFT).ended:
                pass
            assert practice.goal().frame is not None

    # Each team runs its agent over the whole challenge; the server records every episode.
    for token, seed in [("red-secret", "1"), ("blue-secret", "2")]:
        out = tmp_path / f"{token}.jsonl"
        args = ["eval", "--agent", "random", "--seed", seed, "--split", "challenge", "--no-progress"]
        assert main([*args, "--out", str(out), "--server", server.address, "--token", token]) == 0
        # A second run of the same scenes is refused by the server: one counted attempt each.
        again = ["eval", "--agent", "random", "--split", "challenge", "--fresh", "--no-progress"]
        assert (
            main(
                [*again, "--out", str(tmp_path / "again.jsonl"), "--server", server.address, "--token", token]
            )
            == 1
        )
        err = capsys.readouterr().err
        assert "already played" in err
        ids = ", ".join(f"challenge/{i:05d}" for i in range(SCENES))
        refused = f"{SCENES} episodes were refused by the server and not recorded, as they would be again"
        assert f"{refused}: {ids}" in err
        assert "rerun" not in err

    with (
        esrp.Client(server.address, token="red-secret") as red,
        pytest.raises(esrp.AlreadyPlayed, match="already played"),
    ):
        red.create_episode(hidden[0].id)

    red_records = [json.loads(line) for line in (records / "team-red.jsonl").read_text().splitlines()]
    assert sorted(r["scene_id"] for r in red_records) == [s.id for s in hidden]
    assert all(r["counted"] and r["token"] == "team-red" and r["agent"] == "random" for r in red_records)
    # The participant's own file and the server's records agree on every episode.
    own = {
        r["scene_id"]: r for r in map(json.loads, (tmp_path / "red-secret.jsonl").read_text().splitlines())
    }
    for r in red_records:
        assert (r["actions"], r["success"], r["osr"], r["rdr"], r["steps"]) == (
            own[r["scene_id"]]["actions"],
            own[r["scene_id"]]["success"],
            own[r["scene_id"]]["osr"],
            own[r["scene_id"]]["rdr"],
            own[r["scene_id"]]["steps"],
        )

    # The organiser verifies every record on the server (an admin replays any scene).
    capsys.readouterr()
    files = [str(records / "team-red.jsonl"), str(records / "team-blue.jsonl")]
    verify = ["verify", *files, "--server", server.address, "--token", "organiser-secret", "--no-progress"]
    assert main([*verify, "--key", str(records / "records.key")]) == 0
    assert capsys.readouterr().out.endswith(f"{2 * SCENES} records verified, all match\n")
    # A participant's token cannot replay the challenge (its attempts are spent).
    as_red = ["verify", files[0], "--server", server.address, "--token", "red-secret", "--no-progress"]
    assert main(as_red) == 1

    # The server's records are ordinary results files: `esrp report` reads them.
    assert main(["report", files[0], "--out", str(tmp_path / "report")]) == 0
    report = (tmp_path / "report" / "report.md").read_text()
    assert f"`team-red.jsonl` (random, {SCENES} episodes)" in report

    # The leaderboard ranks both teams from the records folder alone.
    page = tmp_path / "leaderboard.html"
    assert main(["report", "--leaderboard", str(records), "--out", str(page)]) == 0
    ranking = capsys.readouterr().out
    assert "team-red" in ranking
    assert "team-blue" in ranking
    html = page.read_text()
    assert 'data-participant="team-red"' in html
    assert 'data-participant="team-blue"' in html
