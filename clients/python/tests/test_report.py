"""`esrp report`: the tables hold hand-computed numbers of a small fixture; the HTML page, loaded
from disk in a real headless Chromium (Playwright driving the system's browser), shows the JSONL's
numbers, the paper's rows, and plots and a replay still that decode to real pictures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import esrp
from esrp.cli import main
from esrp.report import load_runs, write_report
from esrp.results import SCHEMA, EpisodeRecord, Tally, append_record, fixed, read_records

CHROMIUM = Path(os.environ.get("ESRP_CHROMIUM", "/usr/bin/chromium"))


def record(
    agent: str, scene: str, difficulty: str, stage: int, osr: float, rdr: float, steps: int
) -> EpisodeRecord:
    objects = {"easy": 1, "medium": 2, "hard": 4}[difficulty]
    return EpisodeRecord(
        schema=SCHEMA,
        scene_id=scene,
        dataset="fixture",
        split="test",
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
        horizon=300 if difficulty == "hard" else 200,
        end="success" if stage == 4 else "horizon",
        total_reward=0.0,
        actions=[0] * steps,
        wall_seconds=0.5,
        agent_stats={},
        server_version="0.1.0",
        client="fixture",
        finished_at="2026-11-23T00:00:00Z",
    )


FIXTURE = {
    "alpha": [
        record("alpha", "f/1", "easy", 4, 1.0, 0.0, 20),
        record("alpha", "f/2", "easy", 3, 0.0, 1.5, 200),
        record("alpha", "f/3", "medium", 3, 0.5, 0.25, 200),
        record("alpha", "f/4", "hard", 1, 0.0, 1.0, 300),
    ],
    "beta": [
        record("beta", "f/1", "easy", 4, 1.0, 0.1, 30),
        record("beta", "f/2", "easy", 2, 0.0, 1.0, 200),
        record("beta", "f/3", "easy", 3, 0.0, 0.9, 200),
    ],
}

# By hand. alpha: SR 1/4; OSR (1 + 0 + 0.5 + 0) / 4 = 0.375; RDR (0 + 1.5 + 0.25 + 1) / 4 = 0.6875;
# easy SR 1/2, OSR 1/2, RDR 0.75; medium 0 / 0.5 / 0.25; hard 0 / 0 / 1; stages 1, 0, 2, 1 of 4.
# beta: SR 1/3, OSR 1/3, RDR (0.1 + 1 + 0.9) / 3 = 0.6667; all easy; stages 0, 1, 1, 1 of 3.
EXPECTED = {
    "alpha": {
        "episodes": "4",
        "sr": "25.00",
        "osr": "37.50",
        "rdr": "0.6875",
        "easy-episodes": "2",
        "easy-sr": "50.00",
        "easy-osr": "50.00",
        "easy-rdr": "0.7500",
        "medium-episodes": "1",
        "medium-sr": "0.00",
        "medium-osr": "50.00",
        "medium-rdr": "0.2500",
        "hard-episodes": "1",
        "hard-sr": "0.00",
        "hard-osr": "0.00",
        "hard-rdr": "1.0000",
        "stage-1": "25.00",
        "stage-2": "0.00",
        "stage-3": "50.00",
        "stage-4": "25.00",
    },
    "beta": {
        "episodes": "3",
        "sr": "33.33",
        "osr": "33.33",
        "rdr": "0.6667",
        "easy-episodes": "3",
        "easy-sr": "33.33",
        "easy-osr": "33.33",
        "easy-rdr": "0.6667",
        "medium-episodes": "0",
        "medium-sr": "–",
        "hard-sr": "–",
        "stage-1": "0.00",
        "stage-2": "33.33",
        "stage-3": "33.33",
        "stage-4": "33.33",
    },
}


def write_fixture(folder: Path) -> list[Path]:
    paths = []
    for agent, records in FIXTURE.items():
        path = folder / f"{agent}.jsonl"
        with open(path, "wb") as file:
            for r in records:
                append_record(file, r)
        paths.append(path)
    return paths


def expected_cells(records: list[EpisodeRecord]) -> dict[str, str]:
    """The cells a run's rows must show, computed from its records."""
    overall = Tally.of(records)
    cells = {
        "episodes": str(overall.episodes),
        "sr": fixed(100 * overall.sr, 2),
        "osr": fixed(100 * overall.osr, 2),
        "rdr": fixed(overall.rdr, 4),
    }
    for stage in range(1, 5):
        cells[f"stage-{stage}"] = fixed(100 * overall.stage_share(stage), 2)
    for difficulty in ("easy", "medium", "hard"):
        t = Tally.of(r for r in records if r.difficulty == difficulty)
        cells[f"{difficulty}-episodes"] = str(t.episodes)
        if t.episodes:
            cells[f"{difficulty}-sr"] = fixed(100 * t.sr, 2)
            cells[f"{difficulty}-rdr"] = fixed(t.rdr, 4)
    return cells


def test_expected_cells_agree_with_the_hand_computation() -> None:
    for agent, records in FIXTURE.items():
        computed = expected_cells(records)
        assert {k: v for k, v in EXPECTED[agent].items() if k in computed} == {
            k: computed[k] for k in EXPECTED[agent] if k in computed
        }


def test_markdown_tables_hold_the_hand_computed_numbers(tmp_path: Path) -> None:
    paths = write_fixture(tmp_path)
    markdown, page = write_report(paths, tmp_path / "report")
    text = markdown.read_text()
    assert "| **alpha** | 4 | 25.00 | 37.50 | 0.6875 |" in text
    assert "| **beta** | 3 | 33.33 | 33.33 | 0.6667 |" in text
    assert (
        "| **alpha** | 2 | 50.00 | 50.00 | 0.7500 | 1 | 0.00 | 50.00 | 0.2500 | 1 | 0.00 | 0.00 | 1.0000 |"
        in text
    )
    assert "| **beta** | 3 | 33.33 | 33.33 | 0.6667 | 0 | – | – | – | 0 | – | – | – |" in text
    assert "| **alpha** | 25.00 | 0.00 | 50.00 | 25.00 |" in text
    assert "| **beta** | 0.00 | 33.33 | 33.33 | 33.33 |" in text
    assert "| ESRP-PLAN (paper) | – | 30.20 | 36.59 | 0.6916 |" in text
    assert "| ESRP-VLM (paper) | 11.64 | 4.18 | 66.55 | 17.64 |" in text
    for name in ("sr_osr_by_difficulty", "stages", "rdr", "steps_vs_horizon"):
        assert f"(images/{name}.png)" in text
        assert (tmp_path / "report" / "images" / f"{name}.png").stat().st_size > 1000
    assert page.read_text().count('src="data:image/png;base64,') == 4


def test_runs_of_one_agent_are_told_apart_by_their_file(tmp_path: Path) -> None:
    paths = write_fixture(tmp_path)
    again = tmp_path / "alpha-again.jsonl"
    again.write_bytes(paths[0].read_bytes())
    assert [run.label for run in load_runs([*paths, again])] == [
        "alpha (alpha)",
        "beta",
        "alpha (alpha-again)",
    ]


def test_the_html_report_in_a_real_browser(server: esrp.LocalServer, tmp_path: Path) -> None:
    if not CHROMIUM.is_file():
        pytest.skip(f"no Chromium at {CHROMIUM}: apt-get install chromium (scripts/python-tests.sh does)")
    from playwright.sync_api import sync_playwright

    paths = write_fixture(tmp_path)
    real = tmp_path / "random.jsonl"
    args = ["eval", "--agent", "random", "--difficulty", "medium", "--limit", "2", "--seed", "1"]
    assert main([*args, "--out", str(real), "--server", server.address]) == 0
    real_records = read_records(real).records
    still_scene = real_records[0].scene_id
    folder = tmp_path / "report"
    status = main(
        ["report", *map(str, paths), str(real), "--out", str(folder), "--replay-scenes", still_scene]
        + ["--server", server.address]
    )
    assert status == 0
    expected = {**EXPECTED, "random": expected_cells(real_records)}

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=str(CHROMIUM),
            args=["--headless", "--no-sandbox", "--disable-background-networking"],
        )
        try:
            page = browser.new_page(viewport={"width": 1200, "height": 900})
            page.goto((folder / "report.html").as_uri())
            assert page.title() == "ESRP evaluation report"
            for run, cells in expected.items():
                for key, text in cells.items():
                    table = (
                        "#table-stages"
                        if key.startswith("stage")
                        else ("#table-difficulty" if "-" in key else "#table-overall")
                    )
                    cell = page.locator(f'{table} tr[data-run="{run}"] td[data-key="{key}"]')
                    assert cell.inner_text() == text, (run, key)
            paper = page.locator('#table-overall tr[data-paper="ESRP-PLAN (paper)"] td[data-key="sr"]')
            assert paper.inner_text() == "30.20"
            paper_hard = page.locator(
                '#table-difficulty tr[data-paper="ESRP-PLAN (paper)"] td[data-key="hard-osr"]'
            )
            assert paper_hard.inner_text() == "22.00"
            # Self-contained: no script, no stylesheet or image from elsewhere.
            assert page.locator("script, link").count() == 0
            images = page.evaluate(
                """() => Array.from(document.images).map((img) => {
                    const canvas = document.createElement("canvas");
                    canvas.width = img.naturalWidth;
                    canvas.height = img.naturalHeight;
                    const context = canvas.getContext("2d");
                    context.drawImage(img, 0, 0);
                    const data = context.getImageData(0, 0, canvas.width, canvas.height).data;
                    const colours = new Set();
                    for (let i = 0; i < data.length; i += 4 * 7) {
                        colours.add((data[i] << 16) | (data[i + 1] << 8) | data[i + 2]);
                    }
                    return {
                        className: img.className,
                        data: img.src.startsWith("data:image/png;base64,"),
                        complete: img.complete,
                        width: img.naturalWidth,
                        height: img.naturalHeight,
                        colours: colours.size,
                    };
                })"""
            )
            assert [i["className"] for i in images] == ["plot"] * 4 + ["replay"]
            for image in images:
                assert image["data"], image
                assert image["complete"], image
                assert image["width"] > 100, image
                assert image["height"] > 100, image
                assert image["colours"] > 8, image  # not blank
            replay = page.locator(f'figure.replay[data-scene="{still_scene}"] img')
            assert replay.count() == 1
            shot = tmp_path / "report.png"
            page.screenshot(path=str(shot), full_page=True)
            assert shot.stat().st_size > 10_000
        finally:
            browser.close()
