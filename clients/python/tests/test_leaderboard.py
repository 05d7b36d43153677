"""`esrp report --leaderboard`: the ranking of hand-made server records (the first counted attempt
per scene, ties broken by OSR then RDR), and the page, loaded from disk in a real headless Chromium
(Playwright driving the system's browser), showing the ranking and its numbers."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

from esrp.cli import main
from esrp.eval.leaderboard import Sourced, rank, select_counted
from esrp.eval.results import SCHEMA, EpisodeRecord, append_record

CHROMIUM = Path(os.environ.get("ESRP_CHROMIUM", "/usr/bin/chromium"))


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
    (a, b) = sorted(rank(records), key=lambda p: p.name)
    assert (a.overall.episodes, a.overall.successes) == (1, 0)
    assert (b.overall.episodes, b.overall.successes) == (1, 1)
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
    # SR 1 > SR 1/2 (three tied: OSR 0.75 before 0.5; at OSR 0.75, RDR 0.15 before 0.45) > SR 0.
    assert [p.name for p in rank(records)] == [
        "best",
        "high-osr-low-rdr",
        "high-osr-high-rdr",
        "low-osr",
        "worst",
    ]


def test_a_record_without_a_token_belongs_to_its_file() -> None:
    record = server_record("", "challenge/00001", "easy", 4, 1.0, 0.0, "2026-11-23T10:00:00Z")
    del record.extra["token"]
    (participant,) = rank(sourced(record, path="records/team-c.jsonl"))
    assert participant.name == "team-c"


# Two participants' records, as a server with --records writes them (one file per token). By hand:
# team-b: 3 counted scenes (its second attempt at 00001 is not), 2 successes: SR 66.67 %, Wilson
#   20.77–93.85 %; OSR (1 + 1 + 0.5) / 3 = 83.33 %; RDR (0 + 0 + 0.5) / 3 = 0.1667.
# team-a: 3 counted scenes, 1 success: SR 33.33 %, Wilson 6.15–79.23 %; OSR (1 + 0.5 + 0.25) / 3
#   = 58.33 %; RDR (0 + 0.3 + 0.8) / 3 = 0.3667. Its minival and uncounted records do not count.
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
}

EXPECTED: dict[str, dict[str, str]] = {
    "team-b": {
        "rank": "1",
        "episodes": "3 of 3",
        "sr": "66.67",
        "sr-ci": "20.77–93.85",
        "osr": "83.33",
        "rdr": "0.1667",
        "easy-sr": "100.00 (1)",
        "medium-sr": "100.00 (1)",
        "hard-sr": "0.00 (1)",
        "stage-3": "33.33",
        "stage-4": "66.67",
        "agents": "vlm",
        "first": "2026-11-22T10:00:00Z",
        "last": "2026-11-23T19:40:00Z",
        "versions": "esrp-server 0.2.0 on esrp-bench-v2 (hash 0123456789abcdef)",
    },
    "team-a": {
        "rank": "2",
        "episodes": "3 of 3",
        "sr": "33.33",
        "sr-ci": "6.15–79.23",
        "osr": "58.33",
        "rdr": "0.3667",
        "hard-sr": "0.00 (1)",
        "stage-1": "0.00",
        "stage-3": "66.67",
        "agents": "ppo v1, ppo v2",
        "first": "2026-11-20T09:00:00Z",
        "last": "2026-11-21T17:30:00Z",
    },
}


def write_records(folder: Path) -> Path:
    folder.mkdir()
    for token, records in TEAMS.items():
        with open(folder / f"{token}.jsonl", "wb") as file:
            for r in records:
                append_record(file, r)
    (folder / "notes.txt").write_text("not a records file: not read\n")
    return folder


def test_the_leaderboard_page_in_a_real_browser(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = write_records(tmp_path / "records")
    out = tmp_path / "site" / "leaderboard.html"
    assert main(["report", "--leaderboard", str(folder), "--out", str(out)]) == 0
    text = capsys.readouterr().out.splitlines()
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
        "episodes",
    ]
    assert text[1].split() == ["1", "team-b", "66.67", "20.77–93.85", "83.33", "0.1667", "3", "of", "3"]
    assert text[2].split() == ["2", "team-a", "33.33", "6.15–79.23", "58.33", "0.3667", "3", "of", "3"]
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
            rows = page.locator("#leaderboard tbody tr")
            assert rows.count() == 2
            assert [rows.nth(k).get_attribute("data-participant") for k in range(2)] == ["team-b", "team-a"]
            # What a reader sees, in order: rank, name, then the numbers.
            seen: list[Any] = [rows.nth(k).inner_text().split("\t")[:7] for k in range(2)]
            assert seen == [
                ["1", "team-b", "3 of 3", "66.67", "20.77–93.85", "83.33", "0.1667"],
                ["2", "team-a", "3 of 3", "33.33", "6.15–79.23", "58.33", "0.3667"],
            ]
            for team, cells in EXPECTED.items():
                for key, value in cells.items():
                    cell = page.locator(f'#leaderboard tr[data-participant="{team}"] td[data-key="{key}"]')
                    assert cell.inner_text() == value, (team, key)
            plan = page.locator('#references tr[data-paper="ESRP-PLAN (paper)"]')
            assert plan.locator('td[data-key="sr"]').inner_text() == "30.20"
            assert "privileged" in plan.locator("th").inner_text()
            assert page.locator("#references tbody tr").count() == 4
            assert "not ranked" in page.locator("h2").inner_text()
            assert "esrp-server 0.2.0 on esrp-bench-v2" in page.locator("#versions").inner_text()
            # Self-contained: no script, no stylesheet or image from elsewhere.
            assert page.locator("script, link, img").count() == 0
        finally:
            browser.close()


def test_errors_are_one_line_with_status_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    only_minival = tmp_path / "minival"
    only_minival.mkdir()
    with open(only_minival / "team-a.jsonl", "wb") as file:
        append_record(file, TEAMS["team-a"][3])
    cases = [
        ([str(tmp_path / "missing")], "esrp report: no folder"),
        ([str(empty)], f"esrp report: {empty} holds no *.jsonl records"),
        ([str(only_minival)], f"esrp report: {only_minival} holds no counted challenge records"),
    ]
    for args, message in cases:
        capsys.readouterr()
        assert main(["report", "--leaderboard", *args, "--out", str(tmp_path / "x.html")]) == 2
        err = capsys.readouterr().err
        assert err.startswith(message), err
        assert err.count("\n") == 1, err
    assert not (tmp_path / "x.html").exists()
