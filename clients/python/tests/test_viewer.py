"""The server's web viewer (`--http-listen`) in headless Chromium, against the real binary: the
page loads from the server; watching an episode shows the ego view the client received, pixel for
pixel; typing an easy scene's expert trajectory as keys plays it to success; a wrong token gets 401
and one token's viewer never lists another's episodes; without tokens only loopback is served."""

from __future__ import annotations

import base64
import concurrent.futures
import io
import json
import os
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

import esrp
from esrp.cli import main

if TYPE_CHECKING:
    from playwright.sync_api import Browser, Page, Playwright

CHROMIUM = Path(os.environ.get("ESRP_CHROMIUM", "/usr/bin/chromium"))
KEYS = "wsadfr"  # action codes 0..5

TOKENS = """
[[token]]
name = "alice"
secret = "alice-secret"
role = "agent"

[[token]]
name = "tina"
secret = "tina-secret"
role = "trainer"

[[token]]
name = "root"
secret = "root-secret"
role = "admin"
"""


@pytest.fixture(scope="module")
def viewer(tmp_path_factory: pytest.TempPathFactory) -> Iterator[esrp.LocalServer]:
    folder = tmp_path_factory.mktemp("viewer")
    tokens = folder / "tokens.toml"
    tokens.write_text(TOKENS)
    records = folder / "records"
    with esrp.LocalServer(
        "--http-listen", "127.0.0.1:0", "--tokens", str(tokens), "--records", str(records)
    ) as server:
        yield server


def get(
    server: esrp.LocalServer, path: str, token: str | None, body: dict[str, Any] | None = None
) -> tuple[int, Any]:
    """GETs `path` (POSTs `body` as JSON if given) on the viewer's API."""
    assert server.viewer_url is not None
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(server.viewer_url.rstrip("/") + path, data=data)
    if data is not None:
        request.add_header("Content-Type", "application/json")
    if token is not None:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read() or b"{}")


def pixels(data_url: str) -> np.ndarray:
    from PIL import Image

    png = base64.b64decode(data_url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def test_tokens_see_only_what_they_may(viewer: esrp.LocalServer) -> None:
    assert get(viewer, "/api/whoami", None)[0] == 401
    assert get(viewer, "/api/whoami", "wrong")[0] == 401
    assert get(viewer, "/api/whoami", "alice-secret") == (
        200,
        {"caller": "alice", "role": "agent", "open": False},
    )
    with (
        esrp.Client(viewer.address, token="tina-secret") as tina,
        esrp.Client(viewer.address, token="alice-secret") as alice,
    ):
        scene = next(iter(tina.scenes("test", "easy"))).id
        with tina.create_episode(scene) as theirs, alice.create_episode(scene) as mine:

            def listed(token: str) -> set[str]:
                return {e["id"] for e in get(viewer, "/api/episodes", token)[1]}

            assert listed("alice-secret") == {mine.id}
            assert listed("tina-secret") == {theirs.id}
            assert {mine.id, theirs.id} <= listed("root-secret")
            # Another token's episode cannot be watched or stepped.
            status, body = get(viewer, f"/api/episodes/{theirs.id}/watch", "alice-secret")
            assert status == 403
            assert "belongs to another token" in body["error"]


def test_the_servers_records_by_scene(viewer: esrp.LocalServer) -> None:
    # Alice plays a scene in the page and closes it: the server keeps her record (--records).
    status, scenes = get(viewer, "/api/scenes?split=test&difficulty=medium", "alice-secret")
    assert status == 200
    scene = scenes["scenes"][2]["id"]
    status, played = get(viewer, "/api/play", "alice-secret", {"scene": scene})
    assert status == 200
    episode = f"/api/episodes/{played['episode']}"
    for action in (2, 0, 3):
        assert get(viewer, f"{episode}/step", "alice-secret", {"action": action})[0] == 200
    assert get(viewer, f"{episode}/close", "alice-secret", {})[0] == 200

    status, found = get(viewer, f"/api/records?scene={scene}", "alice-secret")
    assert status == 200
    assert [(r["token"], r["scene_id"], r["agent"], r["steps"]) for r in found["records"]] == [
        ("alice", scene, "human", 3)
    ]
    listed = found["records"][0]
    status, record = get(viewer, f"/api/records/alice/{listed['index']}", "alice-secret")
    assert status == 200
    assert (record["schema"], record["actions"], record["token"]) == ("esrp.results/v1", [2, 0, 3], "alice")
    # Another token lists none of hers and cannot read it; an admin can.
    assert get(viewer, f"/api/records?scene={scene}", "tina-secret")[1]["records"] == []
    status, body = get(viewer, f"/api/records/alice/{listed['index']}", "tina-secret")
    assert status == 403
    assert "only its own records" in body["error"]
    assert get(viewer, f"/api/records/alice/{listed['index']}", "root-secret")[1]["actions"] == [2, 0, 3]
    assert get(viewer, "/api/records/alice/9999", "alice-secret")[0] == 404
    assert get(viewer, "/api/records?scene=esrp-bench-v2/99999", "root-secret")[1]["records"] == []
    assert get(viewer, "/api/records", None)[0] == 401


def test_a_replay_seeks_and_ends_with_its_episode(viewer: esrp.LocalServer) -> None:
    """A replay moves to any step (forward by stepping, back by a reset); two replays seek at once,
    each holding only its own lock; closing the replay's episode frees the replay."""
    status, scenes = get(viewer, "/api/scenes?split=test&difficulty=easy", "alice-secret")
    assert status == 200
    actions = [2, 0, 0, 3, 0, 1, 2, 0] * 4
    started = [
        get(viewer, "/api/replay", "alice-secret", {"scene_id": scene["id"], "actions": actions})
        for scene in scenes["scenes"][3:5]
    ]
    assert [s for s, _ in started] == [200, 200], started
    ids = [body["episode"] for _, body in started]

    def seek_to_end(replay: str) -> tuple[int, Any]:
        return get(viewer, f"/api/replay/{replay}/seek", "alice-secret", {"step": 32})

    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        seeks = list(
            pool.map(lambda i: get(viewer, f"/api/replay/{i}/seek", "alice-secret", {"step": 32}), ids)
        )
    assert seeks == [(200, {"step": 32, "steps": 32})] * 2
    assert get(viewer, f"/api/replay/{ids[0]}/seek", "alice-secret", {"step": 5}) == (
        200,
        {"step": 5, "steps": 32},
    )
    for replay in ids:
        assert get(viewer, f"/api/episodes/{replay}/close", "alice-secret", {})[0] == 200
        status, body = get(viewer, f"/api/replay/{replay}/seek", "alice-secret", {"step": 1})
        assert status == 404
        assert "no replay" in body["error"], body


def rss_bytes(pid: int) -> int:
    status = Path(f"/proc/{pid}/status").read_text()
    return int(next(line for line in status.splitlines() if line.startswith("VmRSS:")).split()[1]) * 1024


def test_a_watcher_that_stops_reading_leaves_the_servers_memory_flat(viewer: esrp.LocalServer) -> None:
    """Frames are made only when the previous one was taken: a page that stops reading holds the
    server to one frame in flight, however fast the agent steps."""
    import socket
    from urllib.parse import urlsplit

    assert viewer.viewer_url is not None
    with esrp.Client(viewer.address, token="tina-secret") as tina:
        scene = next(iter(tina.scenes("test", "easy"))).id
        with tina.create_episode(scene, horizon=100_000) as episode:
            url = urlsplit(viewer.viewer_url)
            watcher = socket.socket()
            watcher.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            watcher.connect((url.hostname, url.port))
            request = (
                f"GET /api/episodes/{episode.id}/watch HTTP/1.1\r\nHost: {url.netloc}\r\n"
                "Authorization: Bearer tina-secret\r\n\r\n"
            )
            watcher.sendall(request.encode())
            try:
                assert watcher.recv(12) == b"HTTP/1.1 200", "the watch stream is open (then never read again)"
                turns = [2, 3] * 200
                for a in turns:
                    episode.step(a)
                before = rss_bytes(viewer.pid)
                for a in turns * 4:
                    episode.step(a)
                after = rss_bytes(viewer.pid)
            finally:
                watcher.close()
    # Each unread frame is ~20 KB of JSON: 1,600 steps queued would be ~30 MB.
    assert after - before < 8 * 1024 * 1024, (before, after)


def test_no_viewer_off_loopback_without_tokens() -> None:
    quiet = {"RUST_BACKTRACE": "0", "RUST_LIB_BACKTRACE": "0"}
    server = esrp.LocalServer("--http-listen", "0.0.0.0:0", env=quiet)
    with pytest.raises(esrp.LocalServerError, match="only a loopback address"):
        server.start()


def test_watch_and_play_in_a_real_browser(viewer: esrp.LocalServer, tmp_path: Path) -> None:
    """The page in a real headless Chromium: watching an agent's episode, then playing one. One
    browser session walked through in order, as a user would: each step starts from the page the
    one before left, so it stays one test."""
    if not CHROMIUM.is_file():
        pytest.skip(f"no Chromium at {CHROMIUM}: apt-get install chromium (scripts/python-tests.sh does)")
    from playwright.sync_api import sync_playwright

    assert viewer.viewer_url is not None
    with esrp.Client(viewer.address, token="tina-secret") as tina:
        easy = [s.id for s in tina.scenes("test", "easy")]
        with tina.create_episode(easy[1], privileged=True) as expert_source:
            expert = json.loads(expert_source.privileged_state().scene_json)["expert_trajectory"]
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(
                executable_path=str(CHROMIUM),
                args=["--headless", "--no-sandbox", "--disable-background-networking"],
            )
            try:
                page = browser.new_page(viewport={"width": 1400, "height": 1000})
                page.goto(viewer.viewer_url)
                assert page.title() == "ESRP viewer"
                # The page carries its icon: a browser's request for /favicon.ico would find nothing.
                icon = page.evaluate("document.querySelector('link[rel=icon]')?.href ?? ''")
                assert icon.startswith("data:image/svg+xml,"), icon
                page.fill("#token", "tina-secret")
                page.click("#signin button")
                page.wait_for_function("document.getElementById('who').textContent === 'tina (trainer)'")

                # Watch: a client steps an episode; the page shows what the client saw.
                with tina.create_episode(easy[0]) as episode:
                    last = None
                    for action in [2, 0, 0, 3]:
                        last = episode.step(action).observation
                    assert last is not None
                    row = page.locator(f'#episodes tr[data-episode="{episode.id}"]')
                    row.wait_for()
                    row.click()
                    page.wait_for_function(
                        f"document.getElementById('watch-panel').dataset.episode === '{episode.id}'"
                        " && document.getElementById('watch-panel').dataset.step === '4'"
                    )
                    shown = pixels(page.get_attribute("#ego", "src") or "")
                    assert np.array_equal(shown, np.asarray(last.ego_rgb))
                    # A trainer sees the current layout and the paths too.
                    assert page.locator("#top-figure").is_visible()
                    assert page.locator("#paths polyline").count() >= 1

                # Play: the expert trajectory typed as keys reaches success, and the banner says so.
                page.select_option("#play-difficulty", "easy")
                page.wait_for_function(
                    f"[...document.getElementById('play-scene').options].some(o => o.value === '{easy[1]}')"
                )
                page.select_option("#play-scene", easy[1])
                page.click("#play button")
                page.wait_for_function(
                    "document.getElementById('watch-title').textContent.includes('you are playing')"
                )
                page.locator("body").click(position={"x": 5, "y": 5})
                for action in expert:
                    page.keyboard.press(KEYS[action])
                page.wait_for_function(
                    "document.getElementById('banner').className === 'success'", timeout=30_000
                )
                assert "Success" in page.inner_text("#banner")
                assert page.inner_text('#stats dd[data-key="step"]').startswith(f"{len(expert)} / ")
                # The person's record: offered for download, and replayed to the same metrics.
                page.wait_for_function("document.getElementById('record-link').dataset.record !== undefined")
                line = page.get_attribute("#record-link", "data-record") or ""
                results = tmp_path / "human.jsonl"
                results.write_text(line)

                # Replay: the record loaded from a file, scrubbed to its end and one step back.
                page.set_input_files("#replay-file", str(results))
                page.wait_for_function("document.getElementById('replay-record').options.length === 1")
                page.click("#replay button[type=submit]")
                page.wait_for_selector("#scrub", state="visible")
                end = len(expert)
                page.locator("#scrub-step").evaluate(
                    "(e, v) => { e.value = v; e.dispatchEvent(new Event('change')); }", end
                )
                page.wait_for_function(
                    f"document.getElementById('watch-panel').dataset.step === '{end}'"
                    " && document.getElementById('banner').className === 'success'"
                )
                page.click("#scrub-back")
                page.wait_for_function(f"document.getElementById('watch-panel').dataset.step === '{end - 1}'")
                assert page.locator("#banner").is_hidden()

                # Replay by scene from the server's records: the same run, found without a file.
                page.fill("#replay-scene", easy[1])
                page.click("#replay-find")
                page.wait_for_function(
                    "[...document.getElementById('replay-record').options]"
                    ".some(o => o.textContent.startsWith('" + easy[1] + " — human (tina)'))"
                )
                assert page.locator("#replay-record option").count() == 1
                page.click("#replay button[type=submit]")
                page.wait_for_function(f"document.getElementById('scrub-at').textContent === '0 / {end}'")
                page.locator("#scrub-step").evaluate(
                    "(e, v) => { e.value = v; e.dispatchEvent(new Event('change')); }", end
                )
                page.wait_for_function(
                    f"document.getElementById('watch-panel').dataset.step === '{end}'"
                    " && document.getElementById('banner').className === 'success'"
                )
            finally:
                browser.close()
    record = json.loads(line)
    assert (record["agent"], record["scene_id"], record["success"]) == ("human", easy[1], True)
    assert record["actions"] == expert
    common = ["--server", viewer.address, "--token", "tina-secret"]
    assert (
        main(
            [
                "replay",
                "--results",
                str(results),
                "--scene",
                easy[1],
                "--out",
                str(tmp_path / "h.png"),
                *common,
            ]
        )
        == 0
    )
    assert main(["verify", str(results), "--no-progress", *common]) == 0


def first_frame(server: esrp.LocalServer, episode: str, token: str) -> dict[str, Any]:
    """The first frame of `episode`'s watch stream as `token` sees it."""
    assert server.viewer_url is not None
    request = urllib.request.Request(f"{server.viewer_url.rstrip('/')}/api/episodes/{episode}/watch")
    request.add_header("Authorization", f"Bearer {token}")
    with urllib.request.urlopen(request, timeout=30) as response:
        lines: list[str] = []
        while True:
            line = response.readline().decode().rstrip("\n")
            if not line and any(item.startswith("event: frame") for item in lines):
                break
            if not line:
                lines = []  # an event other than a frame (none is sent before it)
                continue
            lines.append(line)
    data = "".join(item[5:].strip() for item in lines if item.startswith("data:"))
    frame: dict[str, Any] = json.loads(data)
    return frame


def test_a_paper_only_episode_shows_its_watcher_what_its_client_is_told(tmp_path: Path) -> None:
    """On a hidden scene served with the paper's observation, an agent's own watch stream holds
    no placed count, success or accepted flags (its steps' answers do not either); an admin's
    holds them."""
    (tmp_path / "tokens.toml").write_text(TOKENS)
    args = ["--http-listen", "127.0.0.1:0", "--tokens", str(tmp_path / "tokens.toml")]
    args += ["--challenge-seed", "paper-only-watch", "--challenge-scenes", "1", "--minival-scenes", "1"]
    with (
        esrp.LocalServer(*args) as server,
        esrp.Client(server.address, token="alice-secret") as alice,
        alice.create_episode("minival/00000") as episode,
    ):
        for action in (esrp.Action.LEFT, esrp.Action.FORWARD, esrp.Action.RELEASE):
            assert episode.step(action).info.accepted is False  # blanked for the client
        seen = first_frame(server, episode.id, "alice-secret")
        assert [set(action) for action in seen["last_actions"]] == [{"action"}] * 3
        assert (seen["episode"]["placed"], seen["episode"]["success"]) == (0, False)
        admin = first_frame(server, episode.id, "root-secret")
        assert [set(action) for action in admin["last_actions"]] == [{"action", "accepted"}] * 3


def launch(playwright: Playwright) -> Browser:
    """Headless Chromium (Debian's), as the other browser tests start it."""
    return playwright.chromium.launch(
        executable_path=str(CHROMIUM),
        args=["--headless", "--no-sandbox", "--disable-background-networking"],
    )


def sign_in(page: Page, secret: str) -> None:
    page.fill("#token", secret)
    page.click("#signin button")


def shows(page: Page, element: str, test: str, timeout: float = 30_000) -> None:
    """Waits until the text of element `element` passes `test` (a JS expression over `text`)."""
    page.wait_for_function(
        f"(() => {{ const text = document.getElementById('{element}').textContent; return {test}; }})()",
        timeout=timeout,
    )


def live(server: esrp.LocalServer, secret: str) -> set[str]:
    """The ids of the live episodes `secret` sees."""
    status, listed = get(server, "/api/episodes", secret)
    assert status == 200, listed
    return {e["id"] for e in listed}


def test_the_page_under_a_demanding_user(viewer: esrp.LocalServer, tmp_path: Path) -> None:
    """One browser session that does what the first test does not: signs in with a wrong token
    after a good one, watches from the keyboard, narrows a long scene list, uses the browser's
    own shortcuts while playing, loads a file that is no results file, replays more records than a
    token may keep open at once, closes its episode, and reloads the page while playing."""
    if not CHROMIUM.is_file():
        pytest.skip(f"no Chromium at {CHROMIUM}: apt-get install chromium (scripts/python-tests.sh does)")
    from playwright.sync_api import sync_playwright

    assert viewer.viewer_url is not None
    with esrp.Client(viewer.address, token="alice-secret") as alice, sync_playwright() as playwright:
        easy = [s.id for s in alice.scenes("test", "easy")]
        browser = launch(playwright)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.goto(viewer.viewer_url)
            with alice.create_episode(easy[0]) as theirs:
                row = f'#episodes tr[data-episode="{theirs.id}"]'
                # A good token lists the episode; a wrong one after it clears the page and says why.
                sign_in(page, "alice-secret")
                page.wait_for_selector(row)
                sign_in(page, "not-a-token")
                shows(page, "notice", "text.includes('not one the server knows')")
                assert page.locator("#episodes tbody tr").count() == 0
                assert page.inner_text("#who") == "not signed in"
                assert page.evaluate("document.activeElement.id") == "token"

                # Watching from the keyboard: a row takes the focus, and Enter watches it.
                sign_in(page, "alice-secret")
                page.wait_for_selector(row)
                page.focus(row)
                page.keyboard.press("Enter")
                page.wait_for_function(
                    f"document.getElementById('watch-panel').dataset.episode === '{theirs.id}'"
                )

            # A long scene list says it is cut, and an id narrows it.
            page.select_option("#play-split", "train")
            page.select_option("#play-difficulty", "")
            shows(page, "play-count", "text.startsWith('the first 1000 of ')")
            page.fill("#play-find", easy[2])
            shows(page, "play-count", "text === '0 scenes'")
            page.select_option("#play-split", "test")
            shows(page, "play-count", "text === '1 scene'")
            assert page.eval_on_selector("#play-scene", "s => s.value") == easy[2]

            # Play: the browser's shortcuts (Ctrl+R, Ctrl+F, Alt+D) are not moves; the plain keys are.
            page.click("#play button")
            shows(page, "watch-title", "text.includes('you are playing')")
            played = page.get_attribute("#watch-panel", "data-episode")
            shortcut = page.evaluate(
                """["r", "f", "d"].map((key, i) => {
                    const event = new KeyboardEvent("keydown", { key, ctrlKey: i < 2, altKey: i === 2,
                                                                bubbles: true, cancelable: true });
                    document.body.dispatchEvent(event);
                    return event.defaultPrevented;
                })"""
            )
            assert shortcut == [False, False, False], "the page took the browser's shortcuts"
            page.locator("body").click(position={"x": 5, "y": 5})
            page.keyboard.press("a")
            page.wait_for_function("document.getElementById('watch-panel').dataset.step === '1'")
            assert page.locator("#actions li").all_inner_texts() == ["turn left"]

            # A file that is not a results file: the page says which line, and lists nothing.
            bad = tmp_path / "notes.jsonl"
            bad.write_text(json.dumps({"scene_id": easy[3], "actions": [2]}) + "\nthis is no JSON\n")
            page.set_input_files("#replay-file", str(bad))
            shows(page, "notice", "text.includes('line 2: not JSON')")
            assert page.locator("#replay-record option").count() == 0

            # A results file being written (a run still going): its last line, cut short, is
            # skipped and said, as the other readers of results skip it (the page refused the file).
            going = tmp_path / "going.jsonl"
            whole = json.dumps(
                {"schema": "esrp.results/v1", "scene_id": easy[3], "agent": "test", "actions": [2]}
            )
            going.write_text(whole + "\n" + whole[:40])
            page.set_input_files("#replay-file", str(going))
            page.wait_for_function("document.getElementById('replay-record').options.length === 1")
            shows(page, "notice", "text.includes('line 2: cut short (no newline')")
            # A one-line file of something else without its newline is no results file.
            config = tmp_path / "config.json"
            config.write_text(json.dumps({"learning_rate": 0.001}))
            page.set_input_files("#replay-file", str(config))
            shows(page, "notice", "text.includes('line 1: not an esrp.results/v1 record')")
            assert page.locator("#replay-record option").count() == 0

            # More replays one after the other than a token may keep open: each replaces the last
            # (and the first replaces the played episode), so none is refused.
            good = tmp_path / "runs.jsonl"
            good.write_text(
                "".join(
                    json.dumps({"scene_id": easy[k], "agent": "test", "steps": 2, "actions": [2, 3]}) + "\n"
                    for k in range(3, 9)
                )
            )
            page.set_input_files("#replay-file", str(good))
            page.wait_for_function("document.getElementById('replay-record').options.length === 6")
            replays = []
            for k in range(6):
                page.select_option("#replay-record", str(k))
                page.click("#replay button[type=submit]")
                shows(page, "watch-title", f"text.startsWith('{easy[3 + k]} ')")
                replays.append(page.get_attribute("#watch-panel", "data-episode"))
            assert live(viewer, "alice-secret") == {replays[-1]}, (played, replays)

            # The close button closes it, and the page says so.
            page.click("#close")
            shows(page, "banner", "text.startsWith('closed: ')")
            assert page.locator("#close").is_hidden()
            assert page.locator("#scrub").is_hidden()
            assert live(viewer, "alice-secret") == set()

            # Reloading the page while playing closes the played episode.
            page.select_option("#play-scene", easy[2])
            page.click("#play button")
            shows(page, "watch-title", "text.includes('you are playing')")
            assert len(live(viewer, "alice-secret")) == 1
            page.reload()
            shows(page, "who", "text === 'alice (agent)'")
            for _ in range(50):
                if not live(viewer, "alice-secret"):
                    break
                page.wait_for_timeout(100)
            assert live(viewer, "alice-secret") == set()
        finally:
            browser.close()


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def test_the_page_rides_out_a_server_restart(tmp_path: Path) -> None:
    """The server stops while the page watches an episode: the page says it lost the connection,
    reconnects once a server answers on the address again, then lists that server's episodes and
    says the watched one is gone, all without a reload."""
    if not CHROMIUM.is_file():
        pytest.skip(f"no Chromium at {CHROMIUM}: apt-get install chromium (scripts/python-tests.sh does)")
    from playwright.sync_api import sync_playwright

    address = f"127.0.0.1:{free_port()}"
    with sync_playwright() as playwright:
        browser = launch(playwright)
        try:
            page = browser.new_page()
            with esrp.LocalServer("--http-listen", address) as first, esrp.Client(first.address) as client:
                scene = next(iter(client.scenes("test", "easy"))).id
                episode = client.create_episode(scene)
                page.goto(f"http://{address}/")
                page.click(f'#episodes tr[data-episode="{episode.id}"]')
                page.wait_for_function(
                    f"document.getElementById('watch-panel').dataset.episode === '{episode.id}'"
                )
                page.wait_for_function("document.getElementById('ego').src.startsWith('data:image/png')")
            shows(page, "notice", "text.includes('lost the connection')")
            with (
                esrp.LocalServer("--http-listen", address) as second,
                esrp.Client(second.address) as client,
                client.create_episode(scene) as again,
            ):
                page.wait_for_selector(f'#episodes tr[data-episode="{again.id}"]', timeout=20_000)
                assert page.inner_text("#notice") == ""
                shows(page, "banner", "text.startsWith('closed: no episode')", timeout=20_000)
        finally:
            browser.close()
