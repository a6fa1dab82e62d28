// The labelling page: polls /api/state, plays both clips of the current query off one clock,
// and posts answers. No build step, no dependencies.
"use strict";

const COLUMNS = 10; // frames per row of a clip's sheet (rebel_jax.human.clips.COLUMNS)
const $ = (id) => document.getElementById(id);
const answerButtons = Array.from(document.querySelectorAll(".answer"));

let server = null; // the last /api/state
let current = null; // {id, images: {left, right}, shownAt}
let loading = null; // id of the query whose clips are loading
let busy = false; // an answer, undo or finish is in flight
let actions = 0; // actions sent so far: a poll that started before the latest one is stale
const clock = { elapsed: 0, last: null, playing: true, speed: 1, played: false };

function say(text, error = false) {
  $("message").textContent = text;
  $("message").className = error ? "error" : "";
}

async function request(path, body) {
  const response = await fetch(path, {
    method: body === undefined ? "GET" : "POST",
    headers: { "Content-Type": "application/json" },
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  const data = await response.json();
  if (!response.ok) throw new Error(data.error || response.statusText);
  return data;
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

function render() {
  const s = session();
  const training = $("training");
  $("instruction").textContent = server ? server.instruction : "";
  $("labeller").textContent = server ? `labeller: ${server.labeller}` : "";
  if (server) $("budget").textContent = `labels used: ${server.used} of ${server.budget}`;
  if (!server) {
    training.textContent = "connecting…";
  } else if (server.status === "labelling" && !(s && s.closed)) {
    training.textContent = "training paused: waiting for your answers";
    training.className = "pill paused";
  } else if (server.status === "labelling") {
    training.textContent = "training resumes: learning from your answers";
    training.className = "pill running";
  } else if (server.status === "done") {
    training.textContent = "training finished";
    training.className = "pill";
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
  if (next && next.ready && (!current || current.id !== next.id) && loading !== next.id) load(next);
  if (!next && current) current = null;
  $("query").hidden = !(next && current && current.id === next.id);
  $("waiting").hidden = !$("query").hidden || finishing;
  if (!s) {
    $("waiting-text").textContent =
      server && server.status === "done"
        ? "Training has finished. Thank you!"
        : "Training is running; the next feedback session will appear here.";
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
  const ready = Boolean(current && clock.played && !busy && open && !$("query").hidden);
  answerButtons.forEach((b) => (b.disabled = !ready));
  $("undo").disabled = !(open && s.last) || busy;
  $("finish-button").disabled = busy;
  $("gate").textContent = current && !clock.played ? "Watch both clips to the end once, then answer." : "";
  document.body.dataset.played = clock.played ? "1" : "0";
  document.body.dataset.busy = busy ? "1" : "0";
}

function load(query) {
  loading = query.id;
  const images = {};
  const sides = ["left", "right"];
  let count = 0;
  for (const side of sides) {
    const img = new Image();
    img.onload = () => {
      count += 1;
      if (count === sides.length && loading === query.id) {
        loading = null;
        current = { id: query.id, images, shownAt: Date.now() };
        restart();
        render();
      }
    };
    img.onerror = () => {
      loading = null;
      say(`could not load the ${side} clip of ${query.id}`, true);
    };
    img.src = `/clips/${encodeURIComponent(query.id)}/${side}`;
    images[side] = img;
  }
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
    if (!busy && before === actions) {
      server = state;
      if ($("message").className === "error" && /does not answer/.test($("message").textContent)) say("");
    }
  } catch (err) {
    say(`the trainer does not answer (${err.message}); retrying…`, true);
  }
  render();
  setTimeout(poll, 500);
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

// A clicked button loses focus, so that Enter or space later act as shortcuts, not as a second click.
document.addEventListener("click", (event) => {
  const button = event.target.closest("button");
  if (button) button.blur();
});
