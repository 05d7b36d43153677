// The ESRP viewer: lists the live episodes, watches one (ego view, goal, and for trainer and
// admin tokens the current top-down view with paths, IoUs and RDR), and plays one from the
// keyboard. Plain JS, no dependencies; the server's event streams are read with fetch so that
// the bearer token travels in a header.

const ACTIONS = ["forward", "backward", "turn left", "turn right", "fetch", "release"];
const KEYS = { w: 0, s: 1, a: 2, d: 3, f: 4, r: 5 };
const $ = (id) => document.getElementById(id);

let token = sessionStorage.getItem("esrp-token") || "";
let listAbort = null;
let watchAbort = null;
let watching = null; // episode id
let playing = null; // episode id driven from the keyboard (this page's played episode)
let mine = null; // the episode this page started (played or replayed), closed when it starts another
let episodes = [];
let records = []; // the records to replay (from a results file, or the server's)
let replaying = null; // { episode, steps }: this page's replay
let seeking = Promise.resolve();
// The most episode rows drawn at once: a busy server's list is narrowed with the filter.
const MAX_ROWS = 200;
// Seconds between tries to reach the server again after a stream broke.
const RETRY_SECONDS = 2;
const sleep = (seconds) => new Promise((resolve) => setTimeout(resolve, seconds * 1000));

function headers(extra = {}) {
  return token ? { Authorization: `Bearer ${token}`, ...extra } : extra;
}

async function api(path, body) {
  const init = body === undefined
    ? { headers: headers() }
    : { method: "POST", headers: headers({ "Content-Type": "application/json" }), body: JSON.stringify(body) };
  const response = await fetch(path, init);
  const data = await response.json().catch(() => ({}));
  if (!response.ok) throw Object.assign(new Error(data.error || response.statusText), { status: response.status });
  return data;
}

// Reads a server-sent event stream with fetch; calls onEvent(name, data) per event.
async function stream(path, onEvent, signal) {
  const response = await fetch(path, { headers: headers(), signal });
  if (!response.ok) {
    const data = await response.json().catch(() => ({}));
    throw Object.assign(new Error(data.error || response.statusText), { status: response.status });
  }
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += value;
    let end;
    while ((end = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      let name = "message";
      const data = [];
      for (const line of block.split("\n")) {
        if (line.startsWith("event:")) name = line.slice(6).trim();
        else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
      }
      if (data.length) onEvent(name, data.join("\n"));
    }
  }
}

function notice(text) {
  $("notice").textContent = text;
}

// Stops following the server (a token that failed, or another token signing in).
function signOut() {
  if (listAbort) listAbort.abort();
  if (watchAbort) watchAbort.abort();
  listAbort = watchAbort = null;
  watching = playing = mine = replaying = null;
  episodes = [];
  drawEpisodes();
  $("watch-panel").hidden = true;
  $("scrub").hidden = true;
  $("play-scene").replaceChildren();
  $("who").textContent = "not signed in";
}

async function signIn() {
  signOut();
  try {
    const me = await api("/api/whoami");
    $("who").textContent = `${me.caller} (${me.role})`;
    $("who").dataset.role = me.role;
    notice(me.open ? "no token needed: this server has none and serves the viewer on loopback only" : "");
    $("signin").hidden = me.open;
    followEpisodes();
    loadScenes();
  } catch (e) {
    if (e.status === 401) {
      notice("that token is not one the server knows: enter another");
      $("token").focus();
    } else if (e.status === undefined) {
      notice(`cannot reach the server (${e.message}): trying again`);
      setTimeout(signIn, RETRY_SECONDS * 1000);
    } else {
      notice(e.message);
    }
  }
}

// Follows the list of episodes; when the stream breaks (the server stopped, a proxy dropped
// it), says so and reconnects until the server answers again.
async function followEpisodes() {
  if (listAbort) listAbort.abort();
  const abort = new AbortController();
  listAbort = abort;
  let lost = false;
  while (!abort.signal.aborted) {
    try {
      await stream("/api/episodes/events", (name, data) => {
        if (name !== "episodes") return;
        if (lost) {
          lost = false;
          notice("");
        }
        episodes = JSON.parse(data);
        drawEpisodes();
      }, abort.signal);
    } catch (e) {
      if (abort.signal.aborted) return;
      if (e.status === 401) return signIn();
    }
    if (abort.signal.aborted) return;
    lost = true;
    notice("lost the connection to the server: reconnecting…");
    await sleep(RETRY_SECONDS);
  }
}

function drawEpisodes() {
  const filter = $("filter").value.trim().toLowerCase();
  const body = $("episodes").tBodies[0];
  // The row with the keyboard focus keeps it across redraws.
  const focused = document.activeElement?.closest?.("#episodes tr")?.dataset.episode;
  body.replaceChildren();
  const shown = episodes.filter((e) => !filter ||
    `${e.scene} ${e.room_type} ${e.difficulty} ${e.owner} ${e.agent}`.toLowerCase().includes(filter));
  for (const e of shown.slice(0, MAX_ROWS)) {
    const row = body.insertRow();
    row.dataset.episode = e.id;
    row.tabIndex = 0;
    if (e.id === watching) row.classList.add("selected");
    row.setAttribute("aria-selected", String(e.id === watching));
    for (const cell of [e.scene, e.room_type, e.difficulty, `${e.steps} / ${e.horizon}`,
      `${e.placed} / ${e.objects}`, e.holding ? "yes" : "no", e.owner, e.agent, `${Math.round(e.age_seconds)} s`]) {
      row.insertCell().textContent = cell;
    }
    row.addEventListener("click", () => watch(e.id));
    row.addEventListener("keydown", (event) => {
      if (event.key === "Enter" || event.key === " ") {
        event.preventDefault();
        watch(e.id);
      }
    });
    if (e.id === focused) row.focus();
  }
  $("episodes-more").textContent = shown.length > MAX_ROWS
    ? `the first ${MAX_ROWS} of ${shown.length} episodes: narrow them with the filter`
    : (episodes.length && !shown.length ? "no episode matches the filter" : "");
}

function showBanner(text, className = "") {
  $("banner").hidden = false;
  $("banner").className = className;
  $("banner").textContent = text;
}

// Follows one episode's frames; when the stream breaks without the server saying the episode
// closed, says so and reconnects (the episode may be gone then: a restarted server forgot it).
async function watch(id) {
  if (watchAbort) watchAbort.abort();
  const abort = new AbortController();
  watchAbort = abort;
  watching = id;
  $("watch-panel").hidden = false;
  $("banner").hidden = true;
  $("record").hidden = true;
  $("scrub").hidden = !replaying || replaying.episode !== id;
  $("close").hidden = !mine || mine.id !== id;
  $("goal").removeAttribute("src");
  drawEpisodes();
  let closed = false;
  while (!abort.signal.aborted && !closed) {
    try {
      await stream(`/api/episodes/${encodeURIComponent(id)}/watch`, (name, data) => {
        if (name === "frame") drawFrame(JSON.parse(data));
        if (name === "closed") {
          closed = true;
          episodeGone(id, `closed: ${data}`);
        }
      }, abort.signal);
    } catch (e) {
      if (abort.signal.aborted) return;
      if (e.status !== undefined) {
        // The server answered, and it will not show this episode (gone, or not this token's).
        return episodeGone(id, `closed: ${e.message}`);
      }
    }
    if (abort.signal.aborted || closed) return;
    showBanner("lost the connection to the server: reconnecting…", "lost");
    await sleep(RETRY_SECONDS);
  }
}

// This page no longer drives episode `id` (closed, or gone): its controls go.
function forget(id) {
  if (mine && mine.id === id) mine = null;
  if (playing === id) playing = null;
  if (replaying && replaying.episode === id) replaying = null;
  if (watching === id) {
    $("scrub").hidden = true;
    $("close").hidden = true;
    $("watch-title").textContent = $("watch-title").textContent.replace(" (you are playing)", "");
  }
}

// The watched episode `id` is gone: the banner says why.
function episodeGone(id, why) {
  showBanner(why);
  forget(id);
}

// Closes the episode this page started, if any (a new one replaces it; so does leaving the page).
async function closeMine() {
  if (!mine) return;
  const { id } = mine;
  forget(id);
  try {
    await api(`/api/episodes/${encodeURIComponent(id)}/close`, {});
  } catch (e) {
    if (e.status !== 404) notice(e.message); // 404: it is gone already
  }
}

function drawFrame(f) {
  const e = f.episode;
  $("watch-title").textContent = `${e.scene} — ${e.room_type}, ${e.difficulty}${playing === e.id ? " (you are playing)" : ""}`;
  $("watch-panel").dataset.episode = e.id;
  $("watch-panel").dataset.step = e.steps;
  if (f.ego) $("ego").src = f.ego;
  if (f.goal) $("goal").src = f.goal;
  const stats = [["step", `${e.steps} / ${e.horizon}`], ["placed", `${e.placed} / ${e.objects}`],
    ["holding", e.holding ? "yes" : "no"], ["owner", e.owner], ["agent", e.agent]];
  if (f.rdr !== undefined) stats.push(["RDR", f.rdr.toFixed(4)]);
  $("stats").replaceChildren(...stats.flatMap(([k, v]) => {
    const dt = document.createElement("dt");
    dt.textContent = k;
    const dd = document.createElement("dd");
    dd.textContent = v;
    dd.dataset.key = k;
    return [dt, dd];
  }));
  const top = f.top_down !== undefined;
  $("top-figure").hidden = !top;
  $("objects").hidden = !top;
  if (top) {
    $("top").src = f.top_down;
    const line = (points, colour) => points.length < 2 ? "" :
      `<polyline fill="none" stroke="${colour}" stroke-width="2" points="${points.map((p) => p.join(",")).join(" ")}"/>`;
    $("paths").innerHTML = line(f.agent_path, "red") + f.carried_paths.map((c) => line(c.path, "blue")).join("");
    const body = $("objects").tBodies[0];
    body.replaceChildren();
    for (const o of f.objects) {
      const row = body.insertRow();
      row.insertCell().textContent = o.id;
      row.insertCell().textContent = o.iou.toFixed(3);
      row.insertCell().textContent = o.placed ? "yes" : "no";
    }
  }
  $("actions").replaceChildren(...f.last_actions.map((a) => {
    const li = document.createElement("li");
    // `accepted` is left out where the episode's client is not told (a paper-only episode).
    li.textContent = `${ACTIONS[a.action]}${a.accepted === false ? " (rejected)" : ""}`;
    if (a.accepted === false) li.className = "rejected";
    return li;
  }));
  if (e.ended && playing === e.id && $("record").hidden) offerRecord(e);
  if (!e.ended) $("banner").hidden = true;
  if (e.ended) {
    showBanner(e.success
      ? `Success: every object placed in ${e.steps} steps.`
      : `Episode over: ${e.placed} of ${e.objects} placed after ${e.steps} steps.`, e.success ? "success" : "failure");
  }
}

async function offerRecord(e) {
  $("record").hidden = false;
  try {
    const response = await fetch(`/api/episodes/${e.id}/record`, { headers: headers() });
    if (!response.ok) throw new Error((await response.json()).error);
    const line = await response.text();
    const link = $("record-link");
    link.href = URL.createObjectURL(new Blob([line], { type: "application/x-ndjson" }));
    link.download = `human-${e.scene.replaceAll("/", "-")}.jsonl`;
    link.dataset.record = line;
  } catch (error) {
    $("record").hidden = true;
    notice(error.message);
  }
}

let scenesAsked = 0;
async function loadScenes() {
  const query = new URLSearchParams({ split: $("play-split").value, difficulty: $("play-difficulty").value,
    id: $("play-find").value.trim() });
  const asked = ++scenesAsked;
  try {
    const found = await api(`/api/scenes?${query}`);
    if (asked !== scenesAsked) return; // a later choice's answer is the one to show
    $("play-scene").replaceChildren(...found.scenes.map((s) => new Option(`${s.id} (${s.room_type}, ${s.objects})`, s.id)));
    $("play-count").textContent = found.total > found.scenes.length
      ? `the first ${found.scenes.length} of ${found.total} scenes: type part of an id to narrow them`
      : `${found.total} scene${found.total === 1 ? "" : "s"}`;
  } catch (e) {
    notice(e.message);
  }
}

async function play(event) {
  event.preventDefault();
  const scene = $("play-scene").value;
  if (!scene) return notice("no scene chosen: pick a split and difficulty that have some");
  try {
    await closeMine();
    const started = await api("/api/play", { scene });
    playing = started.episode;
    mine = { id: started.episode };
    watch(started.episode);
  } catch (e) {
    notice(e.message);
  }
}

// Replay: a record (from a results file, or the server's records of a scene) re-run on the
// server, scrubbed step by step. Records listed from the server are fetched whole when chosen.

// The records of a results file: every line an esrp.results/v1 record, else a notice of the
// first line that is not one (and no records). A last line without its newline that begins as a
// record line does is a write in progress (a run still going): skipped and said, as the other
// tools that read results files skip it.
const RECORD_START = '{"schema":"esrp.results/v1"';
const mayBeCutRecord = (line) => {
  const squeezed = line.replace(/[ \t\r]/g, "");
  return squeezed.startsWith(RECORD_START) || RECORD_START.startsWith(squeezed);
};
async function readRecords() {
  const file = $("replay-file").files[0];
  if (!file) return;
  records = [];
  $("replay-record").replaceChildren();
  const lines = (await file.text()).split("\n");
  const read = [];
  let skipped = "";
  for (const [i, line] of lines.entries()) {
    if (!line.trim()) continue;
    let r;
    try {
      r = JSON.parse(line);
    } catch {
      if (i === lines.length - 1 && mayBeCutRecord(line)) {
        skipped = `${file.name}, line ${i + 1}: cut short (no newline: a write in progress), skipped`;
        continue;
      }
      return notice(`${file.name}, line ${i + 1}: not JSON, so not a results file (esrp.results/v1 JSON Lines)`);
    }
    if (!r || typeof r.scene_id !== "string" || !Array.isArray(r.actions)) {
      return notice(`${file.name}, line ${i + 1}: not an esrp.results/v1 record (no scene_id or actions)`);
    }
    read.push(r);
  }
  if (!read.length) return notice(`${file.name} holds no records${skipped ? ` (${skipped})` : ""}`);
  records = read;
  notice(skipped);
  $("replay-record").replaceChildren(...records.map((r, i) =>
    new Option(`${r.scene_id} — ${r.agent}, ${r.steps} steps${r.success ? ", success" : ""}`, String(i))));
}

async function findRecords() {
  const scene = $("replay-scene").value.trim();
  try {
    const found = await api(`/api/records?scene=${encodeURIComponent(scene)}`);
    records = found.records;
    $("replay-record").replaceChildren(...records.map((r, i) =>
      new Option(`${r.scene_id} — ${r.agent} (${r.token}), ${r.steps} steps${r.success ? ", success" : ""}, ${r.finished_at}`, String(i))));
    if (!records.length) notice(scene ? `no record of ${scene} here` : "no records here");
    else if (found.total > records.length) notice(`the latest ${records.length} of ${found.total} records`);
  } catch (e) {
    notice(e.message);
  }
}

async function startReplay(event) {
  event.preventDefault();
  let r = records[Number($("replay-record").value)];
  if (!r) return notice("choose a results file (or find the server's records) and a record");
  try {
    if (!r.actions) r = await api(`/api/records/${encodeURIComponent(r.token)}/${r.index}`);
    await closeMine();
    const started = await api("/api/replay", { scene_id: r.scene_id, horizon: r.horizon, actions: r.actions });
    replaying = { episode: started.episode, steps: started.steps };
    mine = { id: started.episode };
    $("scrub").hidden = false;
    $("scrub-step").max = String(started.steps);
    $("scrub-step").value = "0";
    $("scrub-at").textContent = `0 / ${started.steps}`;
    watch(started.episode);
  } catch (e) {
    notice(e.message);
  }
}

function seek(step) {
  if (!replaying) return;
  const { episode, steps } = replaying;
  const target = Math.max(0, Math.min(steps, step));
  $("scrub-step").value = String(target);
  seeking = seeking.then(async () => {
    const at = await api(`/api/replay/${episode}/seek`, { step: target });
    $("scrub-at").textContent = `${at.step} / ${at.steps}`;
  }).catch((e) => notice(e.message));
}

let stepping = Promise.resolve();
function key(event) {
  if (!playing || watching !== playing) return;
  // Typing in a field, and the browser's own shortcuts (Ctrl+R, Ctrl+F, ...), are not moves.
  if (event.ctrlKey || event.metaKey || event.altKey) return;
  if (["INPUT", "SELECT", "TEXTAREA"].includes(event.target.tagName) || event.target.isContentEditable) return;
  const action = KEYS[event.key.toLowerCase()];
  if (action === undefined) return;
  event.preventDefault();
  const episode = playing;
  // One step at a time, in the order typed.
  stepping = stepping.then(() => api(`/api/episodes/${episode}/step`, { action })).catch((e) => notice(e.message));
}

$("signin").addEventListener("submit", async (event) => {
  event.preventDefault();
  await closeMine(); // with the token that started it
  token = $("token").value.trim();
  sessionStorage.setItem("esrp-token", token);
  signIn();
});
$("filter").addEventListener("input", drawEpisodes);
$("play-split").addEventListener("change", loadScenes);
$("play-difficulty").addEventListener("change", loadScenes);
$("play-find").addEventListener("input", loadScenes);
$("close").addEventListener("click", closeMine);
// Leaving the page closes the episode it started (a request that outlives the page).
addEventListener("pagehide", () => {
  if (mine) fetch(`/api/episodes/${encodeURIComponent(mine.id)}/close`, { method: "POST", headers: headers(), keepalive: true });
});
$("play").addEventListener("submit", play);
document.addEventListener("keydown", key);
$("replay-file").addEventListener("change", readRecords);
$("replay").addEventListener("submit", startReplay);
$("replay-find").addEventListener("click", findRecords);
$("scrub-step").addEventListener("change", () => seek(Number($("scrub-step").value)));
$("scrub-back").addEventListener("click", () => seek(Number($("scrub-step").value) - 1));
$("scrub-forward").addEventListener("click", () => seek(Number($("scrub-step").value) + 1));
signIn();
