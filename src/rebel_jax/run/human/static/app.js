// The labelling page: polls /api/state, plays both clips of the current query off one clock,
// and posts answers. No build step, no dependencies. Every API call carries the run's token, read
// from the address the trainer printed (?token=...).
"use strict";

const COLUMNS = 10; // frames per row of a clip's sheet (rebel_jax.human.clips.COLUMNS)
const TIMEOUT_MS = 5000; // a request the trainer has not answered by then counts as not answered
const $ = (id) => document.getElementById(id);
const answerButtons = Array.from(document.querySelectorAll(".answer"));
const TOKEN = new URLSearchParams(window.location.search).get("token") || "";

let server = null; // the last /api/state
let current = null; // {id, images: {left, right}, shownAt, reported}
// The trainer: when it last answered (Date.now()), since when it has not, and why it refuses us (403).
const contact = { last: null, lost: null, refused: null };
let loading = null; // id of the query whose clips are loading
let busy = false; // an answer, undo or finish is in flight
let actions = 0; // actions sent so far: a poll that started before the latest one is stale
const clock = { elapsed: 0, last: null, playing: true, speed: 1, played: false };

function say(text, error = false) {
  $("message").textContent = text;
  $("message").className = error ? "error" : "";
}

class HttpError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

async function send(path, options = {}) {
  // fetch with the token, a time limit, and the trainer's contact kept up to date.
  const headers = TOKEN ? { Authorization: `token ${TOKEN}` } : {};
  if (options.body !== undefined) headers["Content-Type"] = "application/json";
  const abort = new AbortController();
  const timer = setTimeout(() => abort.abort(), TIMEOUT_MS);
  let response;
  try {
    response = await fetch(path, { ...options, headers, cache: "no-store", signal: abort.signal });
  } catch (err) {
    contact.lost = contact.lost || Date.now();
    throw new HttpError(0, "the trainer is not answering");
  } finally {
    clearTimeout(timer);
  }
  contact.last = Date.now();
  contact.lost = response.status >= 500 ? contact.lost || Date.now() : null;
  contact.refused = response.status === 403 ? await errorOf(response) : null;
  if (!response.ok) throw new HttpError(response.status, contact.refused || (await errorOf(response)));
  return response;
}

async function errorOf(response) {
  try {
    return (await response.clone().json()).error || response.statusText;
  } catch (err) {
    return response.statusText;
  }
}

async function request(path, body) {
  const options = body === undefined ? {} : { method: "POST", body: JSON.stringify(body) };
  return (await send(path, options)).json();
}

async function call(path, body) {
  // An action: answers are disabled until the server has it, and polls started before it are dropped.
  busy = true;
  actions += 1;
  updateButtons();
  try {
    return await request(path, body);
  } finally {
    busy = false;
  }
}

function session() {
  return server && server.status === "labelling" ? server.session : null;
}

function pending() {
  const s = session();
  if (!s || s.closed || s.complete) return null;
  return s.queries.find((q) => q.answer === null) || null;
}

function finished() {
  return Boolean(server && (server.status === "done" || server.status === "stopped"));
}

function ago(ms) {
  const s = Math.max(0, Math.round(ms / 1000));
  return s < 120 ? `${s} s` : `${Math.floor(s / 60)} min ${s % 60} s`;
}

function renderAlert() {
  // What keeps the page from labelling: a refused token, or a trainer that does not answer.
  const alert = $("alert");
  let text = "";
  if (contact.refused && !TOKEN) {
    text = "This page needs the run's token: open the URL the trainer printed (…/?token=…), or enter the token below.";
  } else if (contact.refused && /token/.test(contact.refused)) {
    text =
      "The trainer does not accept this page's token. A run started again without --human.token has a new " +
      "one: open the URL it printed, or enter the token below.";
  } else if (contact.refused) {
    text = `The trainer refuses this page: ${contact.refused}.`;
  } else if (contact.lost && !finished()) {
    const last = contact.last
      ? `last contact ${ago(Date.now() - contact.last)} ago, at ${new Date(contact.last).toLocaleTimeString()}`
      : "no contact yet";
    text = `Trainer not answering (${last}); retrying… Answers are disabled until it is back.`;
  }
  alert.textContent = text;
  alert.hidden = !text;
  $("login").hidden = !contact.refused;
  document.body.dataset.contact = contact.refused ? "refused" : contact.lost ? "lost" : contact.last ? "ok" : "";
}

function renderFinished() {
  const done = finished();
  $("finished").hidden = !done;
  if (!done) return;
  const final = server.final;
  let text;
  if (server.status === "done" && final) {
    const value = final.mean === null ? "not a number (a seed diverged)" : final.mean.toFixed(1);
    const spread = final.std === null || final.mean === null ? "" : ` ± ${final.std.toFixed(1)}`;
    text = `Run finished: final evaluation return ${value}${spread}. Thank you!`;
  } else {
    text = "The run stopped before its end (an error or an interrupt): see the trainer's console.";
  }
  $("finished-text").textContent = text;
  $("finished-files").textContent = server.run_dir ? `Its files are in ${server.run_dir}` : "";
  $("finished-exit").hidden = !contact.lost;
}

function render() {
  const s = session();
  const training = $("training");
  renderAlert();
  renderFinished();
  $("instruction").textContent = server ? server.instruction : "";
  $("labeller").textContent = server ? `labeller: ${server.labeller}` : "";
  if (server) $("budget").textContent = `labels used: ${server.used} of ${server.budget}`;
  if (contact.refused) {
    training.textContent = "token refused";
    training.className = "pill stopped";
  } else if (finished()) {
    training.textContent = server.status === "done" ? "run finished" : "run stopped";
    training.className = "pill";
  } else if (contact.lost) {
    training.textContent = "trainer not answering";
    training.className = "pill stopped";
  } else if (!server) {
    training.textContent = "connecting…";
  } else if (server.status === "labelling" && !(s && s.closed)) {
    training.textContent = "training paused: waiting for your answers";
    training.className = "pill paused";
  } else if (server.status === "labelling") {
    training.textContent = "training resumes: learning from your answers";
    training.className = "pill running";
  } else {
    training.textContent = `training running (round ${server.round + 1} of ${server.num_rounds})`;
    training.className = "pill running";
  }
  const next = pending();
  if (s) {
    const answered = s.queries.filter((q) => q.answer !== null).length;
    const k = next ? next.index + 1 : answered;
    $("query-progress").textContent = `query ${k} of ${s.queries.length} (round ${s.round})`;
  } else {
    $("query-progress").textContent = "no session open";
  }
  const finishing = Boolean(s && !s.closed && s.complete);
  $("finish").hidden = !finishing;
  if (finishing) {
    const answered = s.queries.filter((q) => q.answer !== null).length;
    $("finish-text").textContent =
      answered < s.queries.length
        ? `The label budget is spent (${answered} of ${s.queries.length} queries answered).`
        : `All ${s.queries.length} queries of this session are answered.`;
  }
  const reachable = !contact.refused && !contact.lost;
  if (reachable && next && next.ready && (!current || current.id !== next.id) && loading !== next.id) load(next);
  if (!next && current) current = null;
  // A trainer started again (--resume) has not seen the query shown: report it again.
  if (current && next && current.id === next.id && !next.shown && !current.reporting) current.reported = false;
  if (current && !current.reported && !current.reporting && reachable) report(current);
  $("query").hidden = !(next && current && current.id === next.id);
  $("waiting").hidden = !$("query").hidden || finishing || finished() || Boolean(contact.refused);
  if (!server) {
    $("waiting-text").textContent = "Waiting for the trainer…";
  } else if (!s) {
    $("waiting-text").textContent = "Training is running; the next feedback session will appear here.";
  } else if (s.closed) {
    $("waiting-text").textContent = "Answers sent: training goes on. The next session will appear here.";
  } else if (next) {
    $("waiting-text").textContent = "Rendering the clips…";
  }
  document.body.dataset.status = server ? server.status : "";
  document.body.dataset.session = s && !s.closed ? String(s.round) : "";
  document.body.dataset.query = current ? current.id : "";
  updateButtons();
}

function updateButtons() {
  const s = session();
  const open = Boolean(s && !s.closed);
  const reachable = !contact.refused && !contact.lost;
  const ready = Boolean(current && current.reported && clock.played && !busy && open && reachable);
  answerButtons.forEach((b) => (b.disabled = !(ready && !$("query").hidden)));
  $("undo").disabled = !(open && s.last && reachable) || busy;
  $("finish-button").disabled = busy || !reachable;
  $("gate").textContent = current && !clock.played ? "Watch both clips to the end once, then answer." : "";
  document.body.dataset.played = clock.played ? "1" : "0";
  document.body.dataset.busy = busy ? "1" : "0";
}

async function image(path) {
  // A clip's sheet, fetched with the token (an <img src> could not send it in a header).
  const blob = await (await send(path)).blob();
  const url = URL.createObjectURL(blob);
  try {
    const img = new Image();
    await new Promise((resolve, reject) => {
      img.onload = resolve;
      img.onerror = () => reject(new Error("not an image"));
      img.src = url;
    });
    return img;
  } finally {
    URL.revokeObjectURL(url);
  }
}

async function load(query) {
  loading = query.id;
  try {
    const base = `/clips/${encodeURIComponent(query.id)}`;
    const [left, right] = await Promise.all([image(`${base}/left`), image(`${base}/right`)]);
    if (loading !== query.id) return;
    loading = null;
    current = { id: query.id, images: { left, right }, shownAt: Date.now(), reported: false };
    restart();
    render();
  } catch (err) {
    if (loading === query.id) loading = null;
    say(`could not load the clips of ${query.id}: ${err.message}`, true);
  }
}

async function report(entry) {
  // Tells the trainer the query is on screen: it takes answers only for queries shown.
  entry.reporting = true;
  actions += 1; // A poll started before the report would show the query as not shown.
  try {
    await request("/api/shown", { query: entry.id });
    entry.reported = true;
    if ($("message").textContent.startsWith("could not report")) say("");
  } catch (err) {
    say(`could not report ${entry.id} as shown: ${err.message}`, true);
  } finally {
    entry.reporting = false;
  }
  updateButtons();
}

function restart() {
  clock.elapsed = 0;
  clock.last = null;
  clock.playing = true;
  clock.played = false;
  $("pause").textContent = "❚❚ Pause";
  updateButtons();
}

function draw(canvas, image, frame, frames) {
  const columns = Math.min(COLUMNS, frames);
  const rows = Math.ceil(frames / columns);
  const w = image.naturalWidth / columns;
  const h = image.naturalHeight / rows;
  if (canvas.width !== w) canvas.width = w;
  if (canvas.height !== h) canvas.height = h;
  const ctx = canvas.getContext("2d");
  ctx.drawImage(image, (frame % columns) * w, Math.floor(frame / columns) * h, w, h, 0, 0, w, h);
}

function tick(now) {
  const s = session();
  if (current && s) {
    const duration = s.frames / s.fps;
    if (clock.last !== null && clock.playing) clock.elapsed += ((now - clock.last) / 1000) * clock.speed;
    clock.last = now;
    if (clock.elapsed >= duration) {
      if (!clock.played) {
        clock.played = true;
        updateButtons();
      }
      clock.elapsed %= duration;
    }
    const frame = Math.min(s.frames - 1, Math.floor(clock.elapsed * s.fps));
    draw($("clip-left"), current.images.left, frame, s.frames);
    draw($("clip-right"), current.images.right, frame, s.frames);
    $("frame").textContent = `${frame + 1} / ${s.frames}`;
  }
  requestAnimationFrame(tick);
}

async function answer(value) {
  if (!current || answerButtons[0].disabled) return;
  try {
    server = await call("/api/answer", {
      query: current.id,
      answer: value,
      shown_at: current.shownAt,
      answered_at: Date.now(),
    });
    say(`answered ${current.id}: ${value}`);
  } catch (err) {
    say(err.message, true);
  }
  render();
}

async function undo() {
  const s = session();
  if (!s || !s.last || $("undo").disabled) return;
  try {
    server = await call("/api/undo", { query: s.last });
    current = null;
    say(`undid the answer to ${s.last}`);
  } catch (err) {
    say(err.message, true);
  }
  render();
}

async function finish() {
  if ($("finish").hidden || busy) return;
  try {
    server = await call("/api/finish", {});
    say("answers sent; training resumed");
  } catch (err) {
    say(err.message, true);
  }
  render();
}

async function poll() {
  const before = actions;
  try {
    const state = await request("/api/state");
    if (!busy && before === actions) server = state;
  } catch (err) {
    // Said by the alert (renderAlert): a refused token, or a trainer not answering.
  }
  render();
  // Once the run is over, a slow poll: a run resumed with the same --human.token is picked up again.
  setTimeout(poll, finished() ? 5000 : 500);
}

answerButtons.forEach((b) => b.addEventListener("click", () => answer(b.dataset.answer)));
$("replay").addEventListener("click", restartPlayback);
$("pause").addEventListener("click", () => {
  clock.playing = !clock.playing;
  clock.last = null;
  $("pause").textContent = clock.playing ? "❚❚ Pause" : "▶ Play";
});
$("speed").addEventListener("click", () => {
  clock.speed = clock.speed === 1 ? 0.5 : 1;
  $("speed").setAttribute("aria-pressed", String(clock.speed === 0.5));
});
$("undo").addEventListener("click", undo);
$("finish-button").addEventListener("click", finish);

function restartPlayback() {
  // Replay from the first frame; answers stay enabled once both clips have played.
  clock.elapsed = 0;
  clock.last = null;
  clock.playing = true;
  $("pause").textContent = "❚❚ Pause";
}

const KEYS = { ArrowLeft: "left", ArrowRight: "right", ArrowUp: "equal", ArrowDown: "skip" };
document.addEventListener("keydown", (event) => {
  if (event.altKey || event.ctrlKey || event.metaKey) return;
  if (event.target instanceof HTMLInputElement) return; // Typing the token.
  if (event.key in KEYS) {
    event.preventDefault();
    answer(KEYS[event.key]);
  } else if (event.key === " ") {
    event.preventDefault();
    if (current) restartPlayback();
  } else if (event.key === "Backspace") {
    event.preventDefault();
    undo();
  } else if (event.key === "Enter") {
    event.preventDefault();
    finish();
  }
});

poll();
requestAnimationFrame(tick);
setInterval(renderAlert, 1000); // The time since the last contact goes on while a request hangs.

// A clicked button loses focus, so that Enter or space later act as shortcuts, not as a second click.
document.addEventListener("click", (event) => {
  const button = event.target.closest("button");
  if (button) button.blur();
});
