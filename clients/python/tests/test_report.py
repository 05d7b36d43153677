"""`esrp report`: the tables hold hand-computed numbers of a small fixture; the HTML page, loaded
from disk in a real headless Chromium (Playwright driving the system's browser), shows the JSONL's
numbers, the paper's rows, and plots and a replay still that decode to real pictures."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

import esrp
from esrp.cli import main
from esrp.eval import report
from esrp.eval.report import ReportError, load_runs, write_report
from esrp.eval.results import SCHEMA, EpisodeRecord, Tally, append_record, fixed, read_records

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
    # SR 95 % CI, Wilson: 1 of 4 is 4.56–69.94 %, 1 of 3 is 6.15–79.23 % (by hand).
    assert "| **alpha** | 4 | 25.00 | 4.56–69.94 | 37.50 | 0.6875 |" in text
    assert "| **beta** | 3 | 33.33 | 6.15–79.23 | 33.33 | 0.6667 |" in text
    assert (
        "| **alpha** | 2 | 50.00 | 50.00 | 0.7500 | 1 | 0.00 | 50.00 | 0.2500 | 1 | 0.00 | 0.00 | 1.0000 |"
        in text
    )
    assert "| **beta** | 3 | 33.33 | 33.33 | 0.6667 | 0 | – | – | – | 0 | – | – | – |" in text
    assert "| **alpha** | 25.00 | 0.00 | 50.00 | 25.00 |" in text
    assert "| **beta** | 0.00 | 33.33 | 33.33 | 33.33 |" in text
    assert "| ESRP-PLAN (paper, privileged) | – | 30.20 | – | 36.59 | 0.6916 |" in text
    assert "| ESRP-VLM (paper) | 11.64 | 4.18 | 66.55 | 17.64 |" in text
    for name in ("sr_osr_by_difficulty", "stages", "rdr", "solved_by_steps"):
        assert f"(images/{name}.png)" in text
        assert (tmp_path / "report" / "images" / f"{name}.png").stat().st_size > 1000
    assert page.read_text().count('src="data:image/png;base64,') == 4


def test_wilson_interval() -> None:
    from esrp.eval.results import wilson

    # Hand-computed: 1 of 4 at 95 %: centre (0.25 + 0.9604) / 1.9604, half-width 0.8123...
    low, high = wilson(1, 4)
    assert (round(low, 4), round(high, 4)) == (0.0456, 0.6994)
    assert wilson(0, 10)[0] == 0.0
    assert wilson(10, 10)[1] == 1.0  # exactly: a report of an all-success run drew a negative error bar
    for trials in range(1, 60):
        low, high = wilson(trials, trials)
        assert high == 1.0
        assert 0.0 < low < 1.0
    assert wilson(0, 0) == (0.0, 1.0)


def capture_figures(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The report's figures, kept as they are instead of being drawn into PNGs."""
    figures: list[Any] = []

    def keep(figure: Any) -> bytes:  # noqa: ANN401
        figures.append(figure)
        return b"png"

    monkeypatch.setattr(report, "_png", keep)
    return figures


def _legends_and_axes(figure: Any) -> tuple[list[Any], list[Any]]:  # noqa: ANN401
    figure.draw_without_rendering()
    axes = list(figure.axes)
    legends = list(figure.legends) + [a.get_legend() for a in axes if a.get_legend() is not None]
    return legends, axes


def test_plots_keep_their_legends_off_the_data_and_inside_the_picture(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The SR legend covered the bars, and the stage legend was cut off at the picture's edge
    ("4 succes"): every legend now lies inside the figure and outside every plot area."""
    figures = capture_figures(monkeypatch)
    # A long run label widens the stage plot's row labels, which pushed its legend off the picture.
    long = tmp_path / "long.jsonl"
    with open(long, "wb") as file:
        append_record(file, record("my_agents:make_a_careful_agent", "f/1", "easy", 4, 1.0, 0.0, 50))
    write_report([*write_fixture(tmp_path), long], tmp_path / "report")
    assert len(figures) == 4
    for figure in figures:
        legends, axes = _legends_and_axes(figure)
        assert legends, figure
        whole = figure.bbox
        for legend in legends:
            box = legend.get_window_extent()
            assert whole.x0 <= box.x0, (figure, box)
            assert box.x1 <= whole.x1, (figure, box)
            assert whole.y0 <= box.y0, (figure, box)
            assert box.y1 <= whole.y1, (figure, box)
            for area in axes:
                assert not box.overlaps(area.get_window_extent()), (figure, box)


def test_steps_plot_shows_the_share_solved_within_k_steps(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every test horizon is 200, so a plot of steps against the horizon put all failures on one
    point; the plot is now each run's share of episodes solved within k steps."""
    figures = capture_figures(monkeypatch)
    markdown, _ = write_report(write_fixture(tmp_path), tmp_path / "report")
    assert "steps_vs_horizon" not in markdown.read_text()
    assert "(images/solved_by_steps.png)" in markdown.read_text()
    axes = figures[3].axes[0]
    assert axes.get_title() == "Episodes solved within k steps"
    curves = {line.get_label(): line for line in axes.get_lines() if not line.get_label().startswith("_")}
    alpha = curves["alpha (SR 25.00 %)"]
    # alpha solved f/1 in 20 steps: 0 % before, 25 % (its SR) from step 20 on.
    assert list(alpha.get_xdata())[:2] == [0, 20]
    assert list(alpha.get_ydata()) == [0.0, 25.0, 25.0]
    beta = curves["beta (SR 33.33 %)"]
    assert list(beta.get_xdata())[1] == 30
    assert list(beta.get_ydata())[-1] == pytest.approx(100 / 3)


def test_warns_about_different_scene_sets_and_partial_splits_and_marks_privileged_agents(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def bench(agent: str, count: int) -> Path:
        path = tmp_path / f"{agent}.jsonl"
        with open(path, "wb") as file:
            for k in range(count):
                r = record(agent, f"esrp-bench-v1/{k:05d}", "easy", 4 if k % 2 else 1, 0.5, 0.5, 40)
                r.dataset = "esrp-bench-v1"
                append_record(file, r)
        return path

    plan, mine = bench("plan", 4), bench("mine", 6)
    markdown, page = write_report([plan, mine], tmp_path / "report")
    err = capsys.readouterr().err
    assert "esrp report: warning: the runs cover different scenes (plan 4, mine 6; 4 common to all)" in err
    assert "plan covers 4 of the 544 test scenes; the paper's rows are full-test-split figures" in err
    assert "mine covers 6 of the 544 test scenes" in err
    text = markdown.read_text()
    assert "**Read with care:**" in text
    assert "- the runs cover different scenes" in text
    assert "| **plan (privileged)** | 4 | 50.00 |" in text
    assert "| **mine** | 6 | 50.00 |" in text
    assert 'data-run="plan"><th scope="row">plan (privileged)</th>' in page.read_text()
    assert '<div class="warnings">' in page.read_text()
    # Runs over the same scenes: only the partial split is said (2 of 4: 15.00–85.00 %, Wilson).
    assert (
        report.coverage_warnings(load_runs([plan, plan]))
        == [
            "plan (plan) covers 4 of the 544 test scenes; the paper's rows are full-test-split figures "
            "(this run's SR: 50.00 %, 95 % interval 15.00–85.00 %)"
        ]
        * 2
    )


def test_a_run_that_repeats_scenes_is_said_to(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A results file holding some scene more than once (files concatenated, a server's records of
    a token that played a scene again) was averaged without a word, each repeat weighing as another
    scene. Every record still counts, as in esrp eval's and esrp-eval's summaries, but the report
    says so on stderr and in its "Read with care" list, and its runs line gives the scenes."""
    alpha, beta = write_fixture(tmp_path)
    first, second = FIXTURE["alpha"][0], FIXTURE["alpha"][1]
    with open(alpha, "ab") as file:
        for r in (first, first, second):  # f/1 three times, f/2 twice
            append_record(file, r)
    out = tmp_path / "report"
    assert main(["report", str(alpha), str(beta), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    said = (
        "alpha holds 2 scenes more than once (e.g. f/1, recorded 3 times; 3 records beyond one per "
        "scene): its rows count every record, so a repeated scene weighs more than the others"
    )
    assert f"esrp report: warning: {said}\n" in err
    assert "beta holds" not in err
    text = (out / "report.md").read_text()
    assert "**Read with care:**" in text
    assert f"\n- {said}\n" in text
    assert "`alpha.jsonl` (alpha, 7 episodes of 4 scenes (some repeated))" in text
    assert "`beta.jsonl` (beta, 3 episodes)" in text
    assert "| **alpha** | 7 |" in text  # every record counts, as the tools' summaries count them
    page = (out / "report.html").read_text()
    assert '<div class="warnings">' in page
    assert "alpha holds 2 scenes more than once" in page
    assert report.repeated_scenes(load_runs([alpha])[0]) == {"f/1": 3, "f/2": 2}
    assert report.repeated_scenes(load_runs([beta])[0]) == {}


def test_the_servers_records_of_privileged_episodes_say_so(tmp_path: Path) -> None:
    """The server's records of a privileged episode did not say it was one, so esrp report showed
    an agent that read the simulator's state, from the server's records, as an ESRP agent proper
    (esrp eval --privileged marks its own records). They carry `"privileged": true` now, signed
    with the rest, right after `finished_at` as esrp eval writes it; other records lack it. And an
    esrp replay's episodes were recorded `unnamed`; they are `esrp replay`'s now."""
    folder = tmp_path / "records"
    with esrp.LocalServer("--records", str(folder), "--record", "all") as server, server.client() as client:
        scene = next(client.scenes("test", "easy")).id
        for agent, privileged in (("my-reference", True), ("my-agent", False)):
            with client.create_episode(scene, privileged=privileged, agent=agent) as episode:
                episode.step(esrp.Action.LEFT)
        lines = (folder / "anonymous.jsonl").read_text().splitlines()
        assert len(lines) == 2
        assert '"finished_at":' in lines[0]
        assert lines[0].split('"finished_at":')[1].split(",", 2)[1] == '"privileged":true'
        assert '"privileged"' not in lines[1]
        runs = {run.agent: run for run in load_runs([folder / "anonymous.jsonl"])}
        assert runs["my-reference"].shown == "my-reference (privileged)"
        assert runs["my-agent"].shown == "my-agent"
        # Signed as it is written: the records verify with the key.
        key = folder / "records.key"
        args = ["verify", str(folder / "anonymous.jsonl"), "--key", str(key), "--no-progress"]
        assert main([*args, "--server", server.address]) == 0
        # The episodes of esrp verify and esrp replay say whose they are (a replay's were unnamed).
        replay = ["replay", "--results", str(folder / "anonymous.jsonl"), "--scene", scene]
        assert main([*replay, "--out", str(tmp_path / "r.png"), "--server", server.address]) == 0
        agents = [r.agent for r in read_records(folder / "anonymous.jsonl").records]
        assert agents == ["my-reference", "my-agent", "esrp verify", "esrp verify", "esrp replay"]


def test_runs_of_one_agent_are_told_apart_by_their_file(tmp_path: Path) -> None:
    paths = write_fixture(tmp_path)
    again = tmp_path / "alpha-again.jsonl"
    again.write_bytes(paths[0].read_bytes())
    assert [run.label for run in load_runs([*paths, again])] == [
        "alpha (alpha)",
        "beta",
        "alpha (alpha-again)",
    ]


def test_a_file_without_records_is_said_not_dropped_silently(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A run whose every episode failed leaves an empty results file; the report left it out without
    a word, and a report of it alone had nothing to say but that."""
    paths = write_fixture(tmp_path)
    empty = tmp_path / "all-failed.jsonl"
    empty.write_text("")
    assert [run.label for run in load_runs([*paths, empty])] == ["alpha", "beta"]
    assert capsys.readouterr().err == f"esrp report: warning: {empty} holds no records (left out)\n"
    with pytest.raises(ReportError, match="^the results files hold no records$"):
        load_runs([empty])


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
