"""`esrp report --leaderboard`: the ranking of hand-made server records (the first counted attempt
per scene, every scene of the challenge's list scored, an unplayed one a failure; ties broken by
OSR then RDR), the records' signatures checked, and the page, loaded from disk in a real headless
Chromium (Playwright driving the system's browser), showing the ranking and its numbers."""

from __future__ import annotations

import hashlib
import hmac
import json
import os
from pathlib import Path
from typing import Any

import pytest

from esrp.cli import main
from esrp.eval.leaderboard import Sourced, rank, select_counted
from esrp.eval.manifest import MANIFEST, MANIFEST_SCHEMA, ChallengeScenes, ManifestScene
from esrp.eval.results import SCHEMA, EpisodeRecord

CHROMIUM = Path(os.environ.get("ESRP_CHROMIUM", "/usr/bin/chromium"))
KEY = b"a-records-key-of-more-than-16-bytes"

# The challenge: four scenes, two easy, one medium, one hard.
SCENES = {
    "challenge/00001": "easy",
    "challenge/00002": "medium",
    "challenge/00003": "hard",
    "challenge/00004": "easy",
}


def challenge(scenes: dict[str, str] = SCENES) -> ChallengeScenes:
    listed = tuple(
        ManifestScene(s, d, {"easy": 1, "medium": 2, "hard": 4}[d], 200) for s, d in scenes.items()
    )
    return ChallengeScenes(Path("records") / MANIFEST, "0123456789abcdef", {"challenge": "paper"}, listed)


def write_manifest(folder: Path, observations: str = "paper") -> None:
    objects = {"easy": 1, "medium": 2, "hard": 4}
    (folder / MANIFEST).write_text(
        json.dumps(
            {
                "schema": MANIFEST_SCHEMA,
                "dataset_hash": "0123456789abcdef",
                "observations": {"challenge": observations, "minival": "paper"},
                "scenes": [
                    {"id": s, "difficulty": d, "objects": objects[d], "horizon": 200}
                    for s, d in SCENES.items()
                ],
            }
        )
    )


def signed_line(record: EpisodeRecord, key: bytes = KEY) -> bytes:
    """The record's line as the server writes it: compact JSON with the HMAC-SHA256 of it as its
    last member (docs/evaluation.md)."""
    body = record.to_json().encode()
    digest = hmac.new(key, body, hashlib.sha256).hexdigest()
    return body[:-1] + b',"signature":"' + digest.encode() + b'"}\n'


def server_record(
    token: str,
    scene: str,
    difficulty: str,
    stage: int,
    osr: float,
    rdr: float,
    finished_at: str,
    *,
    agent: str = "unnamed",
    split: str = "challenge",
    counted: bool = True,
) -> EpisodeRecord:
    """A record as the server writes it (docs/evaluation.md): its own fields in `extra`."""
    objects = {"easy": 1, "medium": 2, "hard": 4}[difficulty]
    steps = 40 if stage == 4 else 200
    return EpisodeRecord(
        schema=SCHEMA,
        scene_id=scene,
        dataset="esrp-bench-v2",
        split=split,
        room_type="Bedroom",
        difficulty=difficulty,
        objects=objects,
        agent=agent,
        agent_config={},
        seed=None,
        success=stage == 4,
        osr=osr,
        rdr=rdr,
        stage=stage,
        placed=round(osr * objects),
        steps=steps,
        horizon=200,
        end="success" if stage == 4 else "horizon",
        total_reward=1.0,
        actions=[2] * steps,
        wall_seconds=3.5,
        agent_stats={},
        server_version="0.2.0",
        client="esrp-server 0.2.0",
        finished_at=finished_at,
        extra={
            "token": token,
            "started_at": finished_at,
            "dataset_hash": "0123456789abcdef",
            "counted": counted,
        },
        observations="paper",
    )


def sourced(*records: EpisodeRecord, path: str = "records/x.jsonl") -> list[Sourced]:
    return [Sourced(Path(path), line, r) for line, r in enumerate(records, start=1)]


def test_the_first_counted_attempt_per_scene_is_the_one_kept() -> None:
    records = sourced(
        server_record("a", "challenge/00001", "easy", 4, 1.0, 0.0, "2026-11-23T10:00:00Z"),
        # Earlier (fractions of a second sort by value, not as text): this is a's attempt.
        server_record("a", "challenge/00001", "easy", 1, 0.0, 1.0, "2026-11-23T09:59:59.5Z"),
        # Not counted, or not of the challenge split: left out.
        server_record("a", "challenge/00002", "easy", 4, 1.0, 0.0, "2026-11-23T08:00:00Z", counted=False),
        server_record("a", "minival/00001", "easy", 4, 1.0, 0.0, "2026-11-23T08:00:00Z", split="minival"),
        # Another participant's attempt at the same scene counts for them.
        server_record("b", "challenge/00001", "easy", 4, 1.0, 0.0, "2026-11-23T12:00:00+02:00"),
    )
    kept = select_counted(records)
    assert [(s.participant, s.line) for s in kept] == [("a", 2), ("b", 5)]
    (a, b) = sorted(rank(records, challenge()), key=lambda p: p.name)
    assert (a.played().episodes, a.played().successes) == (1, 0)
    assert (b.played().episodes, b.played().successes) == (1, 1)
    # Over all four scenes of the challenge.
    assert (b.overall.episodes, b.overall.successes, b.overall.rdr) == (4, 1, 0.75)
    assert a.first == a.last == "2026-11-23T09:59:59.5Z"


def test_ranking_by_sr_then_osr_then_rdr() -> None:
    def two(token: str, osr: float, rdr: float) -> list[EpisodeRecord]:
        return [
            server_record(token, "challenge/00001", "easy", 4, 1.0, 0.0, "2026-11-23T10:00:00Z"),
            server_record(token, "challenge/00002", "medium", 3, osr, rdr, "2026-11-23T10:01:00Z"),
        ]

    records = sourced(
        *two("low-osr", 0.0, 0.2),
        *two("high-osr-high-rdr", 0.5, 0.9),
        *two("high-osr-low-rdr", 0.5, 0.3),
        server_record("best", "challenge/00001", "easy", 4, 1.0, 0.0, "2026-11-23T10:00:00Z"),
        server_record("worst", "challenge/00001", "easy", 1, 0.0, 1.0, "2026-11-23T10:00:00Z"),
    )
    # Over a challenge of these two scenes, all but "worst" have SR 1/2: "best" played one of the
    # two scenes and succeeded (over both: OSR 0.5, RDR 0.5). OSR 0.75 before 0.5; at OSR 0.75,
    # RDR 0.15 before 0.45; at OSR 0.5, RDR 0.1 before 0.5. Then SR 0.
    two_scenes = challenge({"challenge/00001": "easy", "challenge/00002": "medium"})
    assert [p.name for p in rank(records, two_scenes)] == [
        "high-osr-low-rdr",
        "high-osr-high-rdr",
        "low-osr",
        "best",
        "worst",
    ]
    # Over the scenes played alone (a challenge of one scene), it would lead.
    one_scene = challenge({"challenge/00001": "easy"})
    assert [p.name for p in rank(records, one_scene)][0] == "best"


def test_a_record_without_a_token_belongs_to_its_file() -> None:
    record = server_record("", "challenge/00001", "easy", 4, 1.0, 0.0, "2026-11-23T10:00:00Z")
    del record.extra["token"]
    (participant,) = rank(sourced(record, path="records/team-c.jsonl"), challenge())
    assert participant.name == "team-c"


# Two participants' records, as a server with --records writes them (one file per token), scored
# over the challenge's four scenes (two easy, one medium, one hard). By hand:
# team-b: 3 scenes played of 4 (a second counted record of 00001 is rejected; 00004 unplayed), 2
#   successes: SR 2/4 = 50.00 %, Wilson 15.00–85.00 %; OSR (1 + 1 + 0.5 + 0) / 4 = 62.50 %; RDR
#   (0 + 0 + 0.5 + 1) / 4 = 0.3750. Easy: 1 of 2 played, 1 success: 50.00 %.
# team-a: 3 played of 4, 1 success: SR 25.00 %, Wilson 4.56–69.94 %; OSR (1 + 0.5 + 0.25 + 0) / 4 =
#   43.75 %; RDR (0 + 0.3 + 0.8 + 1) / 4 = 0.5250. Its minival and uncounted records do not count.
# team-c: its one record was altered after signing (a failure made a success): rejected.
TEAMS = {
    "team-a": [
        server_record(
            "team-a", "challenge/00001", "easy", 4, 1.0, 0.0, "2026-11-20T09:00:00Z", agent="ppo v1"
        ),
        server_record(
            "team-a", "challenge/00002", "medium", 3, 0.5, 0.3, "2026-11-20T09:05:00Z", agent="ppo v1"
        ),
        server_record(
            "team-a", "challenge/00003", "hard", 3, 0.25, 0.8, "2026-11-21T17:30:00Z", agent="ppo v2"
        ),
        server_record(
            "team-a", "minival/00001", "easy", 4, 1.0, 0.0, "2026-11-19T08:00:00Z", split="minival"
        ),
        server_record(
            "team-a", "challenge/00004", "easy", 4, 1.0, 0.0, "2026-11-22T08:00:00Z", counted=False
        ),
    ],
    "team-b": [
        server_record("team-b", "challenge/00001", "easy", 4, 1.0, 0.0, "2026-11-22T10:00:00Z", agent="vlm"),
        server_record(
            "team-b", "challenge/00002", "medium", 4, 1.0, 0.0, "2026-11-22T10:10:00Z", agent="vlm"
        ),
        server_record("team-b", "challenge/00003", "hard", 3, 0.5, 0.5, "2026-11-23T19:40:00Z", agent="vlm"),
        server_record("team-b", "challenge/00001", "easy", 1, 0.0, 1.0, "2026-11-24T10:00:00Z", agent="vlm"),
    ],
    "team-c": [server_record("team-c", "challenge/00001", "easy", 1, 0.0, 1.0, "2026-11-22T10:00:00Z")],
}

EXPECTED: dict[str, dict[str, str]] = {
    "team-b": {
        "rank": "1",
        "played": "3 of 4",
        "sr": "50.00",
        "sr-ci": "15.00–85.00",
        "osr": "62.50",
        "rdr": "0.3750",
        "easy-sr": "50.00 (1 of 2)",
        "medium-sr": "100.00 (1 of 1)",
        "hard-sr": "0.00 (1 of 1)",
        "stage-3": "25.00",
        "stage-4": "50.00",
        "observations": "paper",
        "agents": "vlm",
        "first": "2026-11-22T10:00:00Z",
        "last": "2026-11-23T19:40:00Z",
        "versions": "esrp-server 0.2.0 on esrp-bench-v2 (hash 0123456789abcdef)",
    },
    "team-a": {
        "rank": "2",
        "played": "3 of 4",
        "sr": "25.00",
        "sr-ci": "4.56–69.94",
        "osr": "43.75",
        "rdr": "0.5250",
        "easy-sr": "50.00 (1 of 2)",
        "hard-sr": "0.00 (1 of 1)",
        "stage-1": "0.00",
        "stage-3": "50.00",
        "agents": "ppo v1, ppo v2",
        "first": "2026-11-20T09:00:00Z",
        "last": "2026-11-21T17:30:00Z",
    },
}


def write_records(folder: Path, *, key: bool = True) -> Path:
    """TEAMS' files, signed (team-c's line then altered), the scene list and the key file."""
    folder.mkdir()
    for token, records in TEAMS.items():
        lines = b"".join(signed_line(r) for r in records)
        if token == "team-c":
            lines = lines.replace(b'"success":false', b'"success":true')
        (folder / f"{token}.jsonl").write_bytes(lines)
    write_manifest(folder)
    if key:
        (folder / "records.key").write_bytes(KEY + b"\n")
    (folder / "notes.txt").write_text("not a records file: not read\n")
    return folder


def test_the_leaderboard_page_in_a_real_browser(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = write_records(tmp_path / "records")
    out = tmp_path / "site" / "leaderboard.html"
    assert main(["report", "--leaderboard", str(folder), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [
        f"esrp report: rejected {folder / 'team-b.jsonl'}:4: refused: duplicate: a second counted record "
        f"of 'team-b' on challenge/00001 (the first: {folder / 'team-b.jsonl'}:1)",
        f"esrp report: rejected {folder / 'team-c.jsonl'}:1: refused: altered: its signature does not "
        "match its bytes under the key",
    ]
    text = captured.out.splitlines()
    assert text[0].split() == [
        "rank",
        "participant",
        "SR",
        "%",
        "95",
        "%",
        "CI",
        "OSR",
        "%",
        "RDR",
        "scenes",
        "played",
    ]
    assert text[1].split() == ["1", "team-b", "50.00", "15.00–85.00", "62.50", "0.3750", "3", "of", "4"]
    assert text[2].split() == ["2", "team-a", "25.00", "4.56–69.94", "43.75", "0.5250", "3", "of", "4"]
    assert text[3] == str(out)
    if not CHROMIUM.is_file():
        pytest.skip(f"no Chromium at {CHROMIUM}: apt-get install chromium (scripts/python-tests.sh does)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=str(CHROMIUM),
            args=["--headless", "--no-sandbox", "--disable-background-networking"],
        )
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.goto(out.as_uri())
            assert page.title() == "ESRP challenge leaderboard"
            header = page.locator("#leaderboard thead th")
            assert header.nth(2).inner_text() == "scenes played"
            assert header.nth(3).inner_text() == "SR % (all scenes)"
            rows = page.locator("#leaderboard tbody tr")
            assert rows.count() == 2
            assert [rows.nth(k).get_attribute("data-participant") for k in range(2)] == ["team-b", "team-a"]
            # What a reader sees, in order: rank, name, then the numbers.
            seen: list[Any] = [rows.nth(k).inner_text().split("\t")[:7] for k in range(2)]
            assert seen == [
                ["1", "team-b", "3 of 4", "50.00", "15.00–85.00", "62.50", "0.3750"],
                ["2", "team-a", "3 of 4", "25.00", "4.56–69.94", "43.75", "0.5250"],
            ]
            for team, cells in EXPECTED.items():
                for key, value in cells.items():
                    cell = page.locator(f'#leaderboard tr[data-participant="{team}"] td[data-key="{key}"]')
                    assert cell.inner_text() == value, (team, key)
            basis = page.locator("#basis").inner_text()
            assert "all 4 scenes" in basis
            assert "counts as a failure (OSR 0, RDR 1)" in basis
            assert "challenge: paper, minival: paper" in page.locator("#observations").inner_text()
            signatures = page.locator("#signatures").inner_text()
            assert signatures.startswith(f"Signatures checked with the records key {folder / 'records.key'}")
            assert "2 of 10 records rejected" in signatures
            rejected = page.locator("#rejected tbody tr")
            assert rejected.count() == 2
            assert rejected.nth(1).get_attribute("data-where") == f"{folder / 'team-c.jsonl'}:1"
            assert "altered" in rejected.nth(1).inner_text()
            plan = page.locator('#references tr[data-paper="ESRP-PLAN (paper)"]')
            assert plan.locator('td[data-key="sr"]').inner_text() == "30.20"
            assert "privileged" in plan.locator("th").inner_text()
            assert page.locator("#references tbody tr").count() == 4
            assert "esrp-server 0.2.0 on esrp-bench-v2" in page.locator("#versions").inner_text()
            # Self-contained: no script, no stylesheet or image from elsewhere.
            assert page.locator("script, link, img").count() == 0
        finally:
            browser.close()


def test_a_participant_of_the_easy_scenes_alone_ranks_below_one_of_every_scene(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # easy-only: both easy scenes, both solved (100 % of what it played), the others unplayed:
    # 2 of 4. everything: all four played, three solved: 3 of 4.
    folder = tmp_path / "records"
    folder.mkdir()
    write_manifest(folder)
    (folder / "records.key").write_bytes(KEY)
    easy = [
        server_record("easy-only", s, "easy", 4, 1.0, 0.0, f"2026-11-22T10:0{k}:00Z")
        for k, s in enumerate(["challenge/00001", "challenge/00004"])
    ]
    every = [
        server_record(
            "everything",
            s,
            d,
            4 if d != "hard" else 3,
            1.0 if d != "hard" else 0.5,
            0.2,
            f"2026-11-22T11:0{k}:00Z",
        )
        for k, (s, d) in enumerate(SCENES.items())
    ]
    for token, records in (("easy-only", easy), ("everything", every)):
        (folder / f"{token}.jsonl").write_bytes(b"".join(signed_line(r) for r in records))
    out = tmp_path / "leaderboard.html"
    assert main(["report", "--leaderboard", str(folder), "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].split()[:3] == ["1", "everything", "75.00"]
    assert lines[2].split()[:3] == ["2", "easy-only", "50.00"]
    assert lines[2].split()[-3:] == ["2", "of", "4"]
    page = out.read_text()
    assert '<td data-key="easy-sr">100.00 (2 of 2)</td>' in page
    assert '<td data-key="hard-sr">0.00 (0 of 1)</td>' in page


def test_without_a_key_the_leaderboard_is_refused_unless_unsigned(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = write_records(tmp_path / "records", key=False)
    out = tmp_path / "x.html"
    assert main(["report", "--leaderboard", str(folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"esrp report: no records key: {folder / 'records.key'} does not exist"), err
    assert "--unsigned" in err
    assert not out.exists()
    # Unchecked: team-c's altered record is ranked (a success), and the page says so.
    assert main(["report", "--leaderboard", str(folder), "--out", str(out), "--unsigned"]) == 0
    captured = capsys.readouterr()
    err_lines = captured.err.splitlines()
    assert err_lines[0] == "esrp report: signatures not checked (--unsigned, no records key)"
    # The checks that need no key still apply: team-b's second counted record of a scene.
    assert [line.split(":")[0] for line in err_lines[1:]] == ["esrp report"]
    assert "duplicate: a second counted record of 'team-b'" in err_lines[1]
    assert [line.split()[1] for line in captured.out.splitlines()[1:4]] == ["team-b", "team-a", "team-c"]
    assert "Signatures NOT checked" in out.read_text()
    # A key given: another key rejects every record.
    other = tmp_path / "other.key"
    other.write_bytes(b"another-key-of-more-than-16-bytes")
    assert main(["report", "--leaderboard", str(folder), "--out", str(out), "--key", str(other)]) == 2
    err = capsys.readouterr().err
    assert "holds no counted challenge records (split 'challenge', counted true) among its 10 records" in err
    assert err.endswith(", 10 rejected\n"), err


def test_errors_are_one_line_with_status_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    only_minival = tmp_path / "minival"
    only_minival.mkdir()
    (only_minival / "team-a.jsonl").write_bytes(signed_line(TEAMS["team-a"][3]))
    write_manifest(only_minival)
    (only_minival / "records.key").write_bytes(KEY)
    no_manifest = tmp_path / "no-manifest"
    no_manifest.mkdir()
    (no_manifest / "team-a.jsonl").write_bytes(signed_line(TEAMS["team-a"][0]))
    cases = [
        ([str(tmp_path / "missing")], "esrp report: no folder"),
        ([str(empty)], f"esrp report: {empty} holds no *.jsonl records"),
        ([str(only_minival)], f"esrp report: {only_minival} holds no counted challenge records"),
        ([str(no_manifest)], f"esrp report: no {no_manifest / MANIFEST}: the challenge's scene list"),
    ]
    for args, message in cases:
        capsys.readouterr()
        assert main(["report", "--leaderboard", *args, "--out", str(tmp_path / "x.html")]) == 2
        err = capsys.readouterr().err
        assert err.startswith(message), err
        assert err.count("\n") == 1, err
    assert not (tmp_path / "x.html").exists()
    assert main(["report", str(tmp_path / "r.jsonl"), "--out", str(tmp_path), "--unsigned"]) == 2
    assert capsys.readouterr().err == "esrp report: --unsigned only apply with --leaderboard\n"
