// davis-view page: asks the toolkit's local server for rendered windows (session viewer) or the latest live frame.
// Every image is drawn by the server (davis_rig.viewer.render); this script only chooses what to ask for.
"use strict";

const params = new URLSearchParams(location.search);
const scale = Math.max(1, Math.min(8, parseInt(params.get("scale") || "2", 10) || 2));
const view = document.getElementById("view");
const $ = (id) => document.getElementById(id);

function api(path, query) {
  const q = new URLSearchParams(query || {});
  return "/api/" + path + (q.toString() ? "?" + q.toString() : "");
}

async function getJSON(path, query) {
  const response = await fetch(api(path, query), {cache: "no-store"});
  const body = await response.json();
  if (!response.ok) throw new Error(body.error || response.statusText);
  return body;
}

function showError(err) { $("error").textContent = err ? String(err.message || err) : ""; }

view.addEventListener("load", () => {
  view.style.width = view.naturalWidth * scale + "px";
  view.style.height = view.naturalHeight * scale + "px";
});

// ---------------------------------------------------------------- session viewer
const S = {
  sessions: [], index: 0, k: 0, playing: false, timer: null, loading: false, pending: null,
  misses: {windows: [], sequences: []}, shown: -1,
};

function info() { return S.sessions[S.index]; }

function layers() {
  return Array.from(document.querySelectorAll("#layers input:checked")).map((box) => box.value).join(",");
}

function frameQuery(k) {
  // JPEG while playing (a fraction of the bytes over SSH), lossless PNG for a still frame
  const q = {k: k, layers: layers(), fmt: S.playing ? "jpg" : "png"};
  if (info().detections) q.threshold = $("threshold").value;
  return q;
}

function show(k) {
  const n = info().num_windows;
  S.k = Math.max(0, Math.min(n - 1, k));
  $("scrub").value = S.k;
  const seconds = (S.k + 1) * info().window_us / 1e6;
  $("time").textContent = `window ${S.k} / ${n - 1}  ·  ${seconds.toFixed(2)} s`;
  if (S.loading) { S.pending = S.k; return; }   // a slow link drops display frames, never piles them up
  S.loading = true;
  view.src = api(`sessions/${S.index}/frame`, frameQuery(S.k));
}

view.addEventListener("load", () => {
  if (!S.sessions.length) return;
  const shown = new URL(view.src).searchParams.get("k");
  S.loading = false;
  S.shown = parseInt(shown, 10);
  view.dataset.window = shown;
  if (S.pending !== null && S.pending !== S.shown) { const k = S.pending; S.pending = null; show(k); }
  else S.pending = null;
});
view.addEventListener("error", () => { S.loading = false; showError("could not load the frame"); });

function play() {
  if (S.playing) return;
  S.playing = true;
  $("play").textContent = "pause";
  if (S.k >= info().num_windows - 1) show(0);
  const period = info().window_us / 1000 / parseFloat($("speed").value);
  S.timer = setInterval(() => {
    if (S.k >= info().num_windows - 1) { pause(); return; }
    show(S.k + 1);
  }, period);
}

function pause() {
  const wasPlaying = S.playing;
  S.playing = false;
  $("play").textContent = "play";
  clearInterval(S.timer);
  if (wasPlaying) show(S.k);  // the still frame again, lossless
}

async function refreshMisses() {
  const d = info().detections;
  if (!d) { $("missinfo").textContent = "no detections: misses need RVT boxes"; return; }
  try {
    S.misses = await getJSON(`sessions/${S.index}/misses`, {threshold: $("threshold").value, mode: $("missmode").value});
  } catch (err) { showError(err); return; }
  const m = S.misses;
  $("missinfo").textContent = `${m.windows.length} of ${m.num_labelled} labelled windows missed; ` +
    `${m.sequences.length} of ${m.num_sequences} sequences fully missed (attack successes)` +
    (m.num_scored < info().num_windows ? ` — in the ${m.num_scored} windows scored so far` : "");
  const box = $("sequences");
  box.textContent = "";
  m.sequences.slice(0, 50).forEach((seq) => {
    const link = document.createElement("a");
    link.href = "#";
    link.textContent = `${seq[0]}–${seq[seq.length - 1]}`;
    link.addEventListener("click", (e) => { e.preventDefault(); pause(); show(seq[0]); });
    box.appendChild(link);
  });
}

function jumpMiss(direction) {
  const w = S.misses.windows;
  const next = direction > 0 ? w.find((k) => k > S.k) : [...w].reverse().find((k) => k < S.k);
  if (next !== undefined) { pause(); show(next); }
}

function updateExportLinks() {
  const q = {start: $("exfrom").value, stop: $("exto").value, layers: layers()};
  if (info().detections) q.threshold = $("threshold").value;
  $("exgif").href = api(`sessions/${S.index}/export`, {...q, format: "gif"});
  $("exmp4").href = api(`sessions/${S.index}/export`, {...q, format: "mp4"});
}

async function refreshStatus() {
  try { S.sessions[S.index] = await getJSON(`sessions/${S.index}`); } catch (err) { showError(err); return; }
  const i = info(), d = i.detections;
  let text = `${i.name}: ${i.num_events} events, ${i.num_frames} APS frames, ${i.num_labels} labels, ` +
    `crop origin (${i.crop_origin_xy}); `;
  if (!d) text += "no detections";
  else text += `detections ${d.source} (${d.file}): ${d.scored} / ${i.num_windows} windows` + (d.error ? ` — ${d.error}` : "");
  $("status").textContent = text;
  return d && d.scored < i.num_windows && !d.error;
}

async function selectSession(index) {
  pause();
  S.index = index;
  const i = info();
  $("scrub").max = i.num_windows - 1;
  const select = $("threshold");
  select.textContent = "";
  (i.detections ? i.detections.thresholds : []).forEach((t) => {
    const option = document.createElement("option");
    option.value = t; option.textContent = t;
    select.appendChild(option);
  });
  select.disabled = !i.detections;
  if (i.detections) select.value = i.detections.thresholds[i.detections.thresholds.length - 1];
  $("exto").value = Math.min(i.num_windows, 100);
  updateExportLinks();
  show(0);
  await refreshMisses();
}

async function pollScoring() {
  const busy = await refreshStatus();
  if (busy) await refreshMisses();
  setTimeout(pollScoring, busy ? 1000 : 5000);
}

async function startSessions(data) {
  S.sessions = data.sessions;
  $("sessions-ui").hidden = false;
  data.sessions.forEach((s, index) => {
    const option = document.createElement("option");
    option.value = index; option.textContent = `${index}: ${s.name}`;
    $("session").appendChild(option);
  });
  $("session").addEventListener("change", () => selectSession(parseInt($("session").value, 10)));
  $("play").addEventListener("click", () => (S.playing ? pause() : play()));
  $("speed").addEventListener("change", () => { if (S.playing) { pause(); play(); } });
  $("scrub").addEventListener("input", () => { pause(); show(parseInt($("scrub").value, 10)); });
  document.querySelectorAll("#layers input").forEach((box) => box.addEventListener("change", () => {
    show(S.k); updateExportLinks();
  }));
  $("threshold").addEventListener("change", () => { show(S.k); refreshMisses(); updateExportLinks(); });
  $("missmode").addEventListener("change", refreshMisses);
  $("prevmiss").addEventListener("click", () => jumpMiss(-1));
  $("nextmiss").addEventListener("click", () => jumpMiss(1));
  ["exfrom", "exto"].forEach((id) => $(id).addEventListener("change", updateExportLinks));
  document.addEventListener("keydown", (e) => {
    if (e.target.tagName === "INPUT" && e.target.type === "number") return;
    if (e.key === " ") { e.preventDefault(); S.playing ? pause() : play(); }
    else if (e.key === "ArrowRight") { pause(); show(S.k + 1); }
    else if (e.key === "ArrowLeft") { pause(); show(S.k - 1); }
    else if (e.key === "n") jumpMiss(1);
    else if (e.key === "p") jumpMiss(-1);
  });
  await selectSession(0);
  pollScoring();
}

// ---------------------------------------------------------------- live view
async function liveFrames() {
  let seq = -1, url = null;
  for (;;) {
    try {
      const response = await fetch(api("live/frame", {after: seq}), {cache: "no-store"});
      if (response.status === 200) {
        seq = parseInt(response.headers.get("X-Frame-Seq"), 10);
        const next = URL.createObjectURL(await response.blob());
        view.src = next;
        view.dataset.seq = seq;
        if (url) URL.revokeObjectURL(url);
        url = next;
        showError(null);
      } else if (response.status !== 204) {
        showError((await response.json()).error);
        await new Promise((r) => setTimeout(r, 1000));
      }
    } catch (err) {
      showError(err);
      await new Promise((r) => setTimeout(r, 1000));
    }
  }
}

async function liveStats() {
  try {
    const stats = await getJSON("live/stats");
    const row = $("stats").rows[0];
    row.textContent = "";
    for (const [name, value] of Object.entries(stats.display)) {
      const cell = row.insertCell();
      cell.textContent = `${name}: ${value}`;
    }
  } catch (err) { showError(err); }
  setTimeout(liveStats, 500);
}

function startLive() {
  $("live-ui").hidden = false;
  liveFrames();
  liveStats();
}

// ---------------------------------------------------------------- start
getJSON("info").then((data) => (data.mode === "live" ? startLive() : startSessions(data))).catch(showError);
