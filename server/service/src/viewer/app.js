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
let playing = null; // episode id driven from the keyboard
let episodes = [];

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

async function signIn() {
  try {
    const me = await api("/api/whoami");
    $("who").textContent = `${me.caller} (${me.role})`;
    $("who").dataset.role = me.role;
    notice(me.open ? "no token needed: this server has none and serves the viewer on loopback only" : "");
    $("signin").hidden = me.open;
    followEpisodes();
    loadScenes();
  } catch (e) {
    $("who").textContent = "not signed in";
    notice(e.status === 401 ? "enter a token the server knows" : e.message);
  }
}

function followEpisodes() {
  if (listAbort) listAbort.abort();
  listAbort = new AbortController();
  stream("/api/episodes/events", (name, data) => {
    if (name === "episodes") {
      episodes = JSON.parse(data);
      drawEpisodes();
    }
  }, listAbort.signal).catch((e) => { if (e.name !== "AbortError") notice(e.message); });
}

function drawEpisodes() {
  const filter = $("filter").value.trim().toLowerCase();
  const body = $("episodes").tBodies[0];
  body.replaceChildren();
  for (const e of episodes) {
    const text = `${e.scene} ${e.room_type} ${e.difficulty} ${e.owner} ${e.agent}`.toLowerCase();
    if (filter && !text.includes(filter)) continue;
    const row = body.insertRow();
    row.dataset.episode = e.id;
    if (e.id === watching) row.classList.add("selected");
    for (const cell of [e.scene, e.room_type, e.difficulty, `${e.steps} / ${e.horizon}`,
      `${e.placed} / ${e.objects}`, e.holding ? "yes" : "no", e.owner, e.agent, `${Math.round(e.age_seconds)} s`]) {
      row.insertCell().textContent = cell;
    }
    row.addEventListener("click", () => watch(e.id));
  }
}

function watch(id) {
  if (watchAbort) watchAbort.abort();
  watchAbort = new AbortController();
  watching = id;
  if (playing !== id) playing = null;
  $("watch-panel").hidden = false;
  $("banner").hidden = true;
  $("record").hidden = true;
  $("goal").removeAttribute("src");
  drawEpisodes();
  stream(`/api/episodes/${id}/watch`, (name, data) => {
    if (name === "frame") drawFrame(JSON.parse(data));
    if (name === "closed") {
      $("banner").hidden = false;
      $("banner").className = "";
      $("banner").textContent = `closed: ${data}`;
    }
  }, watchAbort.signal).catch((e) => { if (e.name !== "AbortError") notice(e.message); });
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
    $("banner").hidden = false;
    $("banner").className = e.success ? "success" : "failure";
    $("banner").textContent = e.success
      ? `Success: every object placed in ${e.steps} steps.`
      : `Episode over: ${e.placed} of ${e.objects} placed after ${e.steps} steps.`;
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

async function loadScenes() {
  const split = $("play-split").value;
  const difficulty = $("play-difficulty").value;
  try {
    const scenes = await api(`/api/scenes?split=${split}&difficulty=${difficulty}`);
    $("play-scene").replaceChildren(...scenes.map((s) => new Option(`${s.id} (${s.room_type}, ${s.objects})`, s.id)));
  } catch (e) {
    notice(e.message);
  }
}

async function play(event) {
  event.preventDefault();
  try {
    const started = await api("/api/play", { scene: $("play-scene").value });
    playing = started.episode;
    watch(started.episode);
  } catch (e) {
    notice(e.message);
  }
}

// Replay: a record (from a results file, or the server's records of a scene) re-run on the
// server, scrubbed step by step. Records listed from the server are fetched whole when chosen.
let records = [];
let replaying = null; // { episode, steps }
let seeking = Promise.resolve();

async function readRecords() {
  const file = $("replay-file").files[0];
  if (!file) return;
  records = (await file.text()).split("\n").filter((l) => l.trim()).map((l) => JSON.parse(l));
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
    const started = await api("/api/replay", { scene_id: r.scene_id, horizon: r.horizon, actions: r.actions });
    replaying = { episode: started.episode, steps: started.steps };
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
  if (!playing || event.target.tagName === "INPUT" || event.target.tagName === "SELECT") return;
  const action = KEYS[event.key.toLowerCase()];
  if (action === undefined) return;
  event.preventDefault();
  const episode = playing;
  // One step at a time, in the order typed.
  stepping = stepping.then(() => api(`/api/episodes/${episode}/step`, { action })).catch((e) => notice(e.message));
}

$("signin").addEventListener("submit", (event) => {
  event.preventDefault();
  token = $("token").value.trim();
  sessionStorage.setItem("esrp-token", token);
  signIn();
});
$("filter").addEventListener("input", drawEpisodes);
$("play-split").addEventListener("change", loadScenes);
$("play-difficulty").addEventListener("change", loadScenes);
$("play").addEventListener("submit", play);
document.addEventListener("keydown", key);
$("replay-file").addEventListener("change", readRecords);
$("replay").addEventListener("submit", startReplay);
$("replay-find").addEventListener("click", findRecords);
$("scrub-step").addEventListener("change", () => seek(Number($("scrub-step").value)));
$("scrub-back").addEventListener("click", () => seek(Number($("scrub-step").value) - 1));
$("scrub-forward").addEventListener("click", () => seek(Number($("scrub-step").value) + 1));
signIn();
