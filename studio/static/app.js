// Impulse Studio's page: gallery, editor, play, the run's curriculum and its learning curves. Plain JavaScript, no
// build step; the one library is uPlot for the charts (static/vendor/, served by the studio, never fetched).
// The server does all the physics and level work; this file draws the scenes it sends (world metres, y up, the
// arena 5 m square) and turns mouse and keys into requests. docs/studio.md describes the API and the socket.
"use strict";

const ARENA = 5.0;
const TOKEN = new URLSearchParams(location.search).get("token");

// ---------------------------------------------------------------------------------------------------------------
// Talking to the server

async function api(path, body) {
  const headers = {};
  if (TOKEN) headers["X-Impulse-Token"] = TOKEN;
  const init = { headers };
  if (body !== undefined) {
    init.method = "POST";
    headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  const response = await fetch(path, init);
  let data = null;
  try { data = await response.json(); } catch (e) { data = { error: `HTTP ${response.status}` }; }
  if (!response.ok) {
    const error = new Error(data.error || `HTTP ${response.status}`);
    error.problems = data.problems || [];
    throw error;
  }
  return data;
}

// Messages. The header line (#message) says what just happened; an error or a warning goes to the alert bar under
// the header (#alert), where it stays until dismissed, replaced by another, or, once it has been up for
// ALERT_MIN_MS, cleared by the next message: a refusal is never overwritten at once by what follows it.
const ALERT_MIN_MS = 8000;
const alertState = { shownAt: 0 };

function say(text, kind) {
  studio.messages.push(text);  // every message, newest last (for the tests and the console)
  if (studio.messages.length > 100) studio.messages.shift();
  if (kind === "error" || kind === "warning") {
    const bar = document.getElementById("alert");
    document.getElementById("error").textContent = text;
    bar.className = kind;
    bar.hidden = false;
    alertState.shownAt = performance.now();
    return;
  }
  const box = document.getElementById("message");
  box.textContent = text;
  box.className = kind || "";
  if (performance.now() - alertState.shownAt > ALERT_MIN_MS) dismissAlert();
}

function dismissAlert() {
  document.getElementById("alert").hidden = true;
}

function sayError(error) {
  const extra = error.problems && error.problems.length ? "\n" + error.problems.join("\n") : "";
  say(error.message + extra, "error");
}

// `work` (a promise), saying in the header "what ... N s" once it has taken a second, until it settles: no request
// of the page waits in silence (the first edit of a size, say, compiles the editor's operations).
async function waitingFor(what, work) {
  const box = document.getElementById("message");
  const since = performance.now();
  const timer = setInterval(() => {
    box.textContent = `${what} ... ${seconds(performance.now() - since)}`;
    box.className = "ok";
  }, 1000);
  try {
    return await work;
  } finally {
    clearInterval(timer);
  }
}

// Elapsed seconds as the wait notes show them: "12 s".
function seconds(ms) {
  return `${Math.floor(ms / 1000)} s`;
}

// A note that counts the seconds of a wait: `note.start(element, text)` shows "text ... 3 s", updated every second,
// until `stop()`; `set(text)` changes the text, keeping the clock.
function waitNote(element) {
  let timer = null, since = 0, text = "";
  const draw = () => { element.textContent = `${text} ${seconds(performance.now() - since)}`; };
  return {
    start(what) {
      this.stop();
      text = what;
      since = performance.now();
      studio.messages.push(what);
      draw();
      timer = setInterval(draw, 1000);
    },
    set(what) { text = what; draw(); },
    stop(after) { clearInterval(timer); timer = null; element.textContent = after || ""; },
    get running() { return timer !== null; },
  };
}

// ---------------------------------------------------------------------------------------------------------------
// Drawing a scene (the server's JSON: polygons, circles, joints, thrusters)

function darker(hex) {
  const n = parseInt(hex.slice(1), 16);
  const parts = [(n >> 16) & 255, (n >> 8) & 255, n & 255].map((c) => Math.round(c * 0.55));
  return `rgb(${parts.join(",")})`;
}

function drawScene(canvas, scene, options) {
  const opts = options || {};
  const ctx = canvas.getContext("2d");
  const scale = canvas.width / ARENA;
  const offset = opts.offset || [0, 0];
  const px = (p, body) => {
    const moved = body !== undefined && body === opts.moving;
    return [(p[0] + (moved ? offset[0] : 0)) * scale, canvas.height - (p[1] + (moved ? offset[1] : 0)) * scale];
  };
  ctx.fillStyle = "#fff";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  if (!scene) return;
  ctx.lineJoin = "round";
  for (const poly of scene.polygons) {
    ctx.beginPath();
    poly.points.forEach((p, i) => {
      const [x, y] = px(p, poly.body);
      if (i === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y);
    });
    ctx.closePath();
    ctx.fillStyle = poly.colour;
    ctx.fill();
    ctx.lineWidth = poly.body === opts.selected ? 4 : 2;
    ctx.strokeStyle = poly.body === opts.selected ? "#ff9900" : darker(poly.colour);
    ctx.stroke();
  }
  for (const circle of scene.circles) {
    const [cx, cy] = px(circle.centre, circle.body);
    const [mx, my] = px(circle.mark, circle.body);
    ctx.beginPath();
    ctx.arc(cx, cy, circle.radius * scale, 0, 2 * Math.PI);
    ctx.fillStyle = circle.colour;
    ctx.fill();
    ctx.lineWidth = circle.body === opts.selected ? 4 : 2;
    ctx.strokeStyle = circle.body === opts.selected ? "#ff9900" : darker(circle.colour);
    ctx.stroke();
    ctx.beginPath();
    ctx.moveTo(cx, cy);
    ctx.lineTo(mx, my);
    ctx.lineWidth = 2;
    ctx.strokeStyle = darker(circle.colour);
    ctx.stroke();
  }
  const dot = Math.max(2, 0.05 * scale);
  for (const joint of scene.joints) {
    const [x, y] = px(joint.position);
    ctx.beginPath();
    if (joint.welded) ctx.rect(x - dot, y - dot, 2 * dot, 2 * dot); else ctx.arc(x, y, dot, 0, 2 * Math.PI);
    ctx.fillStyle = joint.colour;
    ctx.fill();
    ctx.lineWidth = 1;
    ctx.strokeStyle = "#1e1e1e";
    ctx.stroke();
  }
  for (const thruster of scene.thrusters) {
    const t = thruster.triangle;
    if (thruster.drive > 0) {
      const tail = [(t[1][0] + t[2][0]) / 2, (t[1][1] + t[2][1]) / 2];
      const dir = [t[0][0] - tail[0], t[0][1] - tail[1]];
      const len = Math.hypot(dir[0], dir[1]) || 1;
      const flame = [tail[0] - (dir[0] / len) * 0.2 * thruster.drive, tail[1] - (dir[1] / len) * 0.2 * thruster.drive];
      ctx.beginPath();
      [t[1], t[2], flame].forEach((p, i) => { const [x, y] = px(p); if (i === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y); });
      ctx.closePath();
      ctx.fillStyle = "#ff7800";
      ctx.fill();
    }
    ctx.beginPath();
    t.forEach((p, i) => { const [x, y] = px(p); if (i === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y); });
    ctx.closePath();
    ctx.fillStyle = thruster.colour;
    ctx.fill();
    ctx.lineWidth = 1;
    ctx.strokeStyle = "#1e1e1e";
    ctx.stroke();
  }
}

function canvasToWorld(canvas, event) {
  const rect = canvas.getBoundingClientRect();
  const x = ((event.clientX - rect.left) / rect.width) * ARENA;
  const y = ARENA - ((event.clientY - rect.top) / rect.height) * ARENA;
  return [x, y];
}

function insidePolygon(point, points) {
  let inside = false;
  for (let i = 0, j = points.length - 1; i < points.length; j = i++) {
    const [xi, yi] = points[i];
    const [xj, yj] = points[j];
    if ((yi > point[1]) !== (yj > point[1]) && point[0] < ((xj - xi) * (point[1] - yi)) / (yj - yi) + xi) {
      inside = !inside;
    }
  }
  return inside;
}

function shapeAt(scene, point) {
  for (const circle of [...scene.circles].reverse()) {
    if (Math.hypot(point[0] - circle.centre[0], point[1] - circle.centre[1]) <= circle.radius) return circle;
  }
  for (const poly of [...scene.polygons].reverse()) {
    if (insidePolygon(point, poly.points)) return poly;
  }
  return null;
}

function findShape(scene, body) {
  return scene.polygons.find((p) => p.body === body) || scene.circles.find((c) => c.body === body) || null;
}

// The arena's polygons (floor, walls, ceiling) are the level's first, static polygons: bodies 0 to 3.
function isArena(shape) {
  return shape.radius === undefined && shape.body < 4;
}

// ---------------------------------------------------------------------------------------------------------------
// Pages

const studio = { page: "gallery", sets: [], levels: [], editor: null, play: null, rates: null, messages: [] };
window.studio = studio; // for the browser test and for poking at the page from the console

function show(page) {
  studio.page = page;
  for (const section of document.querySelectorAll(".page")) section.classList.toggle("active", section.id === `page-${page}`);
  for (const tab of document.querySelectorAll(".tab")) tab.classList.toggle("active", tab.dataset.page === page);
  if (page === "run") showRunPage();
}

// ----- Gallery

const galleryNote = { note: null, request: 0 };

async function loadSets() {
  const data = await api("/api/sets");
  studio.sets = data.sets;
  const select = document.getElementById("gallery-set");
  select.innerHTML = "";
  for (const set of data.sets) {
    const option = document.createElement("option");
    option.value = set.id;
    option.textContent = set.unavailable ? `${set.title} (unavailable)` : set.title;
    option.disabled = !!set.unavailable;
    option.title = set.unavailable || "";
    select.appendChild(option);
  }
  await loadGallery(select.value);
}

// A set's cards: the grid is cleared at once (a slow set, such as a run's buffer, never shows the previous set's
// cards while it loads), and only the newest request's answer is drawn.
async function loadGallery(setId) {
  const request = ++galleryNote.request;
  const title = (studio.sets.find((set) => set.id === setId) || { title: setId }).title;
  studio.levels = [];
  document.getElementById("gallery-grid").replaceChildren();
  galleryNote.note = galleryNote.note || waitNote(document.getElementById("gallery-count"));
  galleryNote.note.start(`loading ${title} ...`);
  try {
    const data = await api(`/api/levels?set=${encodeURIComponent(setId)}`);
    if (request !== galleryNote.request) return;
    galleryNote.note.stop();
    studio.levels = data.levels;
    renderGallery();
  } catch (error) {
    if (request !== galleryNote.request) return;
    galleryNote.note.stop(`could not load ${title}`);
    sayError(error);
  }
}

// A solve rate's colour: red at 0, amber at one half, green at 1 (hue 0 to 120 degrees).
function rateColour(rate) {
  return `hsl(${Math.round(120 * Math.max(0, Math.min(1, rate)))}, 80%, 32%)`;
}

function renderGallery() {
  const grid = document.getElementById("gallery-grid");
  const words = document.getElementById("gallery-filter").value.toLowerCase().split(/\s+/).filter(Boolean);
  const shown = studio.levels.filter((level) => {
    const text = `${level.name} ${level.size}`.toLowerCase();
    return words.every((word) => text.includes(word));
  });
  grid.innerHTML = "";
  for (const level of shown) {
    const card = document.createElement("div");
    card.className = "card";
    card.dataset.name = level.name;
    const counts = level.problem ? "" :
      `${level.shapes} shapes, ${level.joints} joints, ${level.thrusters} thrusters`;
    card.innerHTML = `<img loading="lazy" alt=""><div class="name"></div><div class="meta"></div>` +
      `<div class="problem"></div><div class="actions"><button class="edit">Edit</button>` +
      `<button class="play">Play</button></div>`;
    card.querySelector("img").src = level.thumbnail;
    card.querySelector(".name").textContent = level.name;
    card.querySelector(".meta").textContent = `size ${level.size}${counts ? " \u00b7 " + counts : ""}`;
    card.querySelector(".problem").textContent = level.problem || "";
    const rates = studio.rates;
    if (rates && rates.set === level.set) {
      const rate = document.createElement("div");
      rate.className = "rate";
      if (level.name in rates.rates) {
        const value = rates.rates[level.name];
        rate.textContent = `agent solves ${Math.round(value * 100)}% (${rates.attempts} attempts)`;
        rate.style.color = rateColour(value);
        rate.dataset.rate = value;
        const bar = document.createElement("div");
        bar.className = "rate-bar";
        bar.style.width = `${Math.max(2, value * 100)}%`;
        bar.style.background = rateColour(value);
        rate.appendChild(bar);
      } else {
        rate.textContent = `agent: ${rates.skipped[level.name] || "not scored"}`;
        rate.classList.add("skipped");
      }
      card.querySelector(".meta").after(rate);
    }
    card.querySelector(".edit").addEventListener("click", (e) => { e.stopPropagation(); openInEditor(level.set, level.name); });
    card.querySelector(".play").addEventListener("click", (e) => { e.stopPropagation(); openInPlay({ set: level.set, name: level.name }); });
    card.addEventListener("click", () => openInEditor(level.set, level.name));
    grid.appendChild(card);
  }
  document.getElementById("gallery-count").textContent = `${shown.length} of ${studio.levels.length} levels`;
}

// Scoring: the request waits for the whole set; meanwhile the page asks every second how far it is (what it
// compiles, levels scored) and shows that with the seconds it has taken.
async function loadSolveRates() {
  const checkpoint = document.getElementById("gallery-agent").value;
  const setId = document.getElementById("gallery-set").value;
  if (!checkpoint) {
    studio.rates = null;
    renderGallery();
    return;
  }
  const query = new URLSearchParams({ set: setId, checkpoint });
  const note = waitNote(document.getElementById("gallery-progress"));
  note.start(`scoring ${checkpoint} on ${setId} ...`);
  const poll = setInterval(async () => {
    try {
      const { progress } = await api(`/api/solve_rates/progress?${query}`);
      if (progress && note.running) {
        const count = progress.total ? ` \u00b7 ${progress.scored} of ${progress.total} levels scored` : "";
        note.set(`scoring ${checkpoint} on ${setId}: ${progress.what}${count} \u00b7`);
      }
    } catch (error) { /* the scoring's own request reports failures */ }
  }, 1000);
  try {
    const data = await api(`/api/solve_rates?${query}`);
    studio.rates = { set: setId, ...data };
    const scored = Object.values(data.rates);
    const mean = scored.length ? scored.reduce((a, b) => a + b, 0) / scored.length : 0;
    note.stop();
    say(`${data.agent} on ${setId}: mean solve rate ${Math.round(mean * 100)}% over ${scored.length} levels`, "ok");
    renderGallery();
  } catch (error) {
    note.stop();
    sayError(error);
  } finally {
    clearInterval(poll);
  }
}

// ----- Editor

// The role buttons and "fixed" choose what the next added shape is; they never change a shape already in the
// level. "Apply to selected" gives the selected shape the chosen role and fixed state (one undoable edit).
const editor = {
  doc: null, scene: null, title: "", tool: "select", role: "neutral", fixed: false, selected: null, warnings: [],
  undo: [], redo: [], drag: null, busy: false, actuators: { joints: [], thrusters: [] }, jointFrom: null,
};
studio.editor = editor;

async function openInEditor(setId, name) {
  try {
    const doc = await waitingFor(`opening ${setId} / ${name}`,
      api(`/api/level?set=${encodeURIComponent(setId)}&name=${encodeURIComponent(name)}`));
    const state = await waitingFor(`opening ${setId} / ${name}`, api("/api/edit", { level: doc, ops: [] }));
    editor.undo = [];
    editor.redo = [];
    editor.selected = null;
    editor.title = `${setId} / ${name}`;
    document.getElementById("editor-name").value = name.split("/").pop();
    setEditorState(state);
    show("editor");
    say(`opened ${editor.title}`, "ok");
  } catch (error) {
    sayError(error);
  }
}

function setEditorState(state) {
  editor.doc = state.level;
  editor.scene = state.scene;
  editor.size = state.size;
  editor.counts = state.counts;
  editor.problems = state.problems;
  editor.warnings = state.warnings || [];
  editor.actuators = state.actuators || { joints: [], thrusters: [] };
  if (editor.selected !== null && !findShape(editor.scene, editor.selected)) editor.selected = null;
  renderEditor();
}

// The joints' and thrusters' table: every change is one edit operation.
function renderActuators() {
  const table = document.getElementById("editor-actuators");
  table.innerHTML = "";
  const { joints, thrusters } = editor.actuators;
  if (!joints.length && !thrusters.length) return;
  const row = (cells) => {
    const tr = document.createElement("tr");
    for (const cell of cells) {
      const td = document.createElement("td");
      if (typeof cell === "string") td.textContent = cell; else td.appendChild(cell);
      tr.appendChild(td);
    }
    table.appendChild(tr);
  };
  const input = (value, onChange, attrs = {}) => {
    const element = document.createElement("input");
    Object.assign(element, { type: "number", step: "0.1", size: 3, value, ...attrs });
    element.addEventListener("change", () => onChange(element));
    return element;
  };
  const check = (checked, onChange) => {
    const element = document.createElement("input");
    Object.assign(element, { type: "checkbox", checked });
    element.addEventListener("change", () => onChange(element.checked));
    return element;
  };
  const remove = (op) => {
    const button = document.createElement("button");
    button.textContent = "\u2715";
    button.title = "delete";
    button.addEventListener("click", () => edit([op]));
    return button;
  };
  row(["joint", "shapes", "motor", "speed", "power", "limits", "key", ""]);
  for (const j of joints) {
    const set = (fields) => edit([{ op: "set_joint", joint: j.joint, ...fields }]);
    const limits = document.createElement("input");
    Object.assign(limits, { size: 8, value: j.limits ? j.limits.join(", ") : "", placeholder: "min, max" });
    limits.addEventListener("change", () => {
      const parts = limits.value.split(",").map((x) => Number(x.trim()));
      set({ limits: limits.value.trim() ? parts : null });
    });
    row([`${j.joint}${j.weld ? " (weld)" : ""}`, `${j.a}\u2013${j.b}`,
      j.weld ? "" : check(j.motor, (motor) => set({ motor })),
      j.weld ? "" : input(j.speed, (e) => set({ speed: Number(e.value) })),
      j.weld ? "" : input(j.power, (e) => set({ power: Number(e.value) }), { min: 0 }),
      j.weld ? "" : limits,
      j.weld ? "" : input(j.binding, (e) => set({ binding: Number(e.value) }), { step: 1, min: 0, max: 3 }),
      remove({ op: "delete_joint", joint: j.joint })]);
  }
  row(["thruster", "shape", "", "", "power", "direction \u00b0", "key", ""]);
  for (const t of thrusters) {
    const set = (fields) => edit([{ op: "set_thruster", thruster: t.thruster, ...fields }]);
    const degrees = Math.round(t.angle * 180 / Math.PI);
    row([`${t.thruster}`, `${t.body}`, "", "", input(t.power, (e) => set({ power: Number(e.value) }), { min: 0 }),
      input(degrees, (e) => set({ angle: Number(e.value) * Math.PI / 180 }),
        { step: 15, min: -360, max: 360, title: "the world direction it pushes: 90 is up, 0 is right" }),
      input(t.binding, (e) => set({ binding: Number(e.value) }), { step: 1, min: 0, max: 1 }),
      remove({ op: "delete_thruster", thruster: t.thruster })]);
  }
}

function renderEditor() {
  const title = document.getElementById("editor-title");
  title.textContent = editor.title || "no level open";
  title.title = editor.title || "";
  drawScene(document.getElementById("editor-canvas"), editor.scene, {
    selected: editor.selected, moving: editor.drag ? editor.drag.body : undefined,
    offset: editor.drag ? editor.drag.offset : [0, 0],
  });
  for (const button of document.querySelectorAll(".tool")) button.classList.toggle("active", button.dataset.tool === editor.tool);
  const shape = editor.scene && editor.selected !== null ? findShape(editor.scene, editor.selected) : null;
  for (const button of document.querySelectorAll(".role")) button.classList.toggle("active", button.dataset.role === editor.role);
  document.getElementById("editor-fixed").checked = editor.fixed;
  const apply = document.getElementById("editor-apply-role");
  apply.disabled = !shape;
  apply.title = shape ? `make body ${shape.body} ${editor.role}${editor.fixed ? ", fixed" : ", free"}` :
    "select a shape first: this gives it the chosen role and fixed state";
  const info = document.getElementById("editor-info");
  if (!editor.doc) { info.textContent = ""; return; }
  const c = editor.counts;
  const picked = shape ? `selected: body ${shape.body}, ${shape.role} ${shape.radius !== undefined ? "circle" : "polygon"}` +
    `${shape.fixed ? ", fixed" : ""}` : "nothing selected";
  info.textContent = `size ${editor.size}: ${c.polygons} polygons, ${c.circles} circles, ${c.joints} joints, ` +
    `${c.thrusters} thrusters \u00b7 ${picked}`;
  const problems = document.getElementById("editor-problems");
  problems.innerHTML = "";
  for (const problem of editor.problems) {
    const item = document.createElement("li");
    item.textContent = problem;
    problems.appendChild(item);
  }
  const warnings = document.getElementById("editor-warnings");
  warnings.replaceChildren(...editor.warnings.map((warning) => {
    const item = document.createElement("li");
    item.textContent = warning;
    return item;
  }));
  document.getElementById("editor-size").value = (editor.size || "").toLowerCase();
  document.getElementById("editor-undo").disabled = editor.undo.length === 0;
  document.getElementById("editor-redo").disabled = editor.redo.length === 0;
  document.getElementById("editor-material").hidden = !shape;
  if (editor.jointFrom !== null) info.textContent += ` \u00b7 joint from body ${editor.jointFrom}: click the second shape`;
  renderActuators();
}

async function edit(ops, size) {
  if (!editor.doc || editor.busy) return;
  editor.busy = true;
  try {
    const what = size ? `moving the level into size ${size.toUpperCase()}` : `${ops.map((op) => op.op).join(", ")}`;
    const state = await waitingFor(what, api("/api/edit", size ? { level: editor.doc, ops, size } : { level: editor.doc, ops }));
    editor.undo.push({ level: editor.doc, scene: editor.scene, size: editor.size, counts: editor.counts, problems: editor.problems });
    editor.redo = [];
    setEditorState(state);
    say(size ? `the level is now size ${state.size}` : `${ops.map((op) => op.op).join(", ")}: done`, "ok");
  } catch (error) {
    sayError(error);
  } finally {
    editor.busy = false;
    renderEditor();
  }
}

function undoRedo(from, to) {
  if (!from.length) return;
  to.push({ level: editor.doc, scene: editor.scene, size: editor.size, counts: editor.counts, problems: editor.problems });
  setEditorState(from.pop());
}

// Save writes the level even when it cannot be solved (a level being built may lack its goal for a while), and
// then warns; the title becomes the saved level's name.
async function saveLevel() {
  const name = document.getElementById("editor-name").value.trim();
  if (!editor.doc) return;
  try {
    const saved = await waitingFor(`saving ${name}`, api("/api/save", { name, level: editor.doc }));
    editor.savedAs = saved.saved;
    editor.title = `${saved.saved.set} / ${saved.saved.name}`;
    renderEditor();
    say(`saved as ${saved.saved.set} / ${saved.saved.name} (${saved.path})`, "ok");
    if (saved.warnings && saved.warnings.length) say(`saved, but ${saved.warnings.join("; ")}`, "warning");
  } catch (error) {
    sayError(error);
  }
}

function setupEditor() {
  const canvas = document.getElementById("editor-canvas");
  for (const button of document.querySelectorAll(".tool")) {
    button.addEventListener("click", () => { editor.tool = button.dataset.tool; renderEditor(); });
  }
  for (const button of document.querySelectorAll(".role")) {
    button.addEventListener("click", () => {
      editor.role = button.dataset.role;
      renderEditor();
    });
  }
  document.getElementById("editor-fixed").addEventListener("change", (event) => {
    editor.fixed = event.target.checked;
    renderEditor();
  });
  document.getElementById("editor-apply-role").addEventListener("click", () => {
    const shape = editor.selected !== null ? findShape(editor.scene, editor.selected) : null;
    if (!shape) { say("select a shape first", "error"); return; }
    const ops = [];
    if (shape.role !== editor.role) ops.push({ op: "set_role", body: shape.body, role: editor.role });
    if (shape.fixed !== editor.fixed && !isArena(shape)) ops.push({ op: "set_fixed", body: shape.body, fixed: editor.fixed });
    if (ops.length) edit(ops); else say(`body ${shape.body} is ${editor.role}${editor.fixed ? " and fixed" : ""} already`, "ok");
  });
  const rotate = (angle) => { if (editor.selected !== null) edit([{ op: "rotate", body: editor.selected, angle }]); };
  document.getElementById("editor-rotate-left").addEventListener("click", () => rotate(Math.PI / 12));
  document.getElementById("editor-rotate-right").addEventListener("click", () => rotate(-Math.PI / 12));
  const resize = (scale) => { if (editor.selected !== null) edit([{ op: "resize", body: editor.selected, scale }]); };
  document.getElementById("editor-shrink").addEventListener("click", () => resize(0.8));
  document.getElementById("editor-grow").addEventListener("click", () => resize(1.25));
  document.getElementById("material-apply").addEventListener("click", () => {
    if (editor.selected === null) return;
    const op = { op: "set_material", body: editor.selected };
    for (const name of ["density", "friction", "restitution"]) {
      const value = document.getElementById(`material-${name}`).value;
      if (value !== "") op[name] = Number(value);
    }
    edit([op]);
  });
  document.getElementById("editor-delete").addEventListener("click", () => {
    if (editor.selected !== null) edit([{ op: "delete", body: editor.selected }]);
  });
  document.getElementById("editor-undo").addEventListener("click", () => undoRedo(editor.undo, editor.redo));
  document.getElementById("editor-redo").addEventListener("click", () => undoRedo(editor.redo, editor.undo));
  document.getElementById("editor-save").addEventListener("click", saveLevel);
  document.getElementById("editor-size").addEventListener("change", (event) => edit([], event.target.value));
  document.getElementById("editor-send").addEventListener("click", async () => {
    if (!editor.doc) return;
    const run = curriculum.run;
    say(`sending the level to run ${run}'s curriculum ...`, "ok");
    const button = document.getElementById("editor-send");
    button.disabled = true;
    try {
      const sent = await waitingFor(`sending the level to run ${run}'s curriculum`, api("/api/inject", { level: editor.doc }));
      say(`in the run's curriculum buffer: slot ${sent.slot}, level ${sent.level_id}` +
        `${sent.evicted ? " (in place of its lowest-scored level)" : ""}`, "ok");
    } catch (error) {
      say(`run ${run} did not take the level`, "ok");
      sayError(error);
    } finally {
      button.disabled = false;
    }
  });
  document.getElementById("editor-play").addEventListener("click", () => {
    if (editor.doc) openInPlay({ level: editor.doc }, editor.title + " (edited)");
  });

  canvas.addEventListener("pointerdown", (event) => {
    if (!editor.scene) return;
    const point = canvasToWorld(canvas, event);
    const fixed = editor.fixed;
    if (editor.tool === "circle") {
      edit([{ op: "add_circle", x: point[0], y: point[1], radius: 0.25, role: editor.role, fixed }]);
      return;
    }
    if (editor.tool === "box" || editor.tool === "triangle") {
      edit([{ op: "add_polygon", x: point[0], y: point[1], width: 0.5, height: 0.5, role: editor.role, fixed,
        sides: editor.tool === "box" ? 4 : 3 }]);
      return;
    }
    if (editor.tool === "joint" || editor.tool === "thruster") {
      const target = shapeAt(editor.scene, point);
      if (!target) { say("click on a shape", "error"); return; }
      if (editor.tool === "thruster") {
        edit([{ op: "add_thruster", body: target.body, x: point[0], y: point[1], angle: Math.PI / 2 }]);
      } else if (editor.jointFrom === null) {
        editor.jointFrom = target.body;
        renderEditor();
      } else {
        const a = editor.jointFrom;
        editor.jointFrom = null;
        const weld = document.getElementById("editor-weld").checked;
        edit([{ op: "add_joint", a, b: target.body, x: point[0], y: point[1], ...(weld ? { weld } : { motor: true }) }]);
      }
      return;
    }
    const shape = shapeAt(editor.scene, point);
    editor.selected = shape ? shape.body : null;
    if (shape) {
      editor.drag = { body: shape.body, start: point, offset: [0, 0] };
      canvas.setPointerCapture(event.pointerId);
    }
    renderEditor();
  });
  canvas.addEventListener("pointermove", (event) => {
    if (!editor.drag) return;
    const point = canvasToWorld(canvas, event);
    editor.drag.offset = [point[0] - editor.drag.start[0], point[1] - editor.drag.start[1]];
    renderEditor();
  });
  canvas.addEventListener("pointerup", () => {
    const drag = editor.drag;
    editor.drag = null;
    if (drag && Math.hypot(drag.offset[0], drag.offset[1]) > 0.005) {
      edit([{ op: "move", body: drag.body, dx: drag.offset[0], dy: drag.offset[1] }]);
    } else {
      renderEditor();
    }
  });
}

// ----- Play

// Keys -> the multi-discrete action: 4 motors (0 off, 1 forwards, 2 backwards), then 2 thrusters (0 off, 1 on).
const KEYS = {
  ArrowRight: [0, 1], ArrowLeft: [0, 2],
  KeyD: [1, 1], KeyA: [1, 2],
  KeyL: [2, 1], KeyJ: [2, 2],
  KeyX: [3, 1], KeyZ: [3, 2],
  ArrowUp: [4, 1], KeyW: [4, 1],
  ArrowDown: [5, 1], KeyS: [5, 1],
};
const KEY_HELP = [
  ["motor 0", "\u2190 \u2192", 0], ["motor 1", "A D", 1], ["motor 2", "J L", 2], ["motor 3", "Z X", 3],
  ["thruster 0", "\u2191 or W", 4], ["thruster 1", "\u2193 or S", 5],
];

// The play socket. Every message gets one reply (a state or an error), matched by its seq; the page steps only when
// no reply is outstanding, so it never runs ahead of the server. Every message asks for progress ("progress":
// true): a reply that takes longer than a second is preceded by a progress message a second saying what the
// server is doing (loading the agent, compiling on first use), which the page shows over the canvas with the
// seconds it has waited; a wait with no word from the server is shown too. Replies to what an older load
// started (steps of the previous level) are dropped. One socket at a time: a socket that is still opening is
// waited for, never opened twice, and a replaced socket's events are ignored.
const play = {
  socket: null, ready: false, opening: null, source: null, title: "", frame: null, held: new Set(),
  running: false, nextStep: 0, period: 1000 / 30, speed: 1, seq: 0, pending: new Map(), loadSeq: 0, rtts: [],
  stepMs: [], controls: { motors: [], thrusters: [] }, agentDrives: false, agent: null, steps: 0, episodes: 0,
  lastOutcome: null, waitShown: "", waits: [],
};
studio.play = play;
const WAIT_SHOWN_AFTER_MS = 1000;

function socketUrl() {
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  return `${scheme}//${location.host}/ws/play${TOKEN ? "?token=" + encodeURIComponent(TOKEN) : ""}`;
}

function connect() {
  if (play.socket && play.ready) return Promise.resolve();
  if (play.opening) return play.opening;
  const socket = new WebSocket(socketUrl());
  play.socket = socket;
  play.opening = new Promise((resolve, reject) => {
    socket.addEventListener("open", () => {
      if (socket !== play.socket) return;
      play.ready = true;
      play.opening = null;
      resolve();
    });
    socket.addEventListener("message", (event) => { if (socket === play.socket) onMessage(event.data); });
    socket.addEventListener("close", () => {
      if (socket !== play.socket) return;
      const wasOpen = play.ready;
      play.ready = false;
      play.opening = null;
      play.pending.clear();
      play.socket = null;
      if (!wasOpen) reject(new Error("the play connection could not be opened: is the studio still running?"));
      say("play connection closed; it reopens when you load a level", "error");
    });
  });
  return play.opening;
}

function send(message) {
  play.seq += 1;
  message.seq = play.seq;
  message.progress = true;
  play.pending.set(play.seq, { sent: performance.now(), type: message.type, progress: null });
  if (message.type === "load" || message.type === "agent") play.loadSeq = play.seq;
  play.socket.send(JSON.stringify(message));
}

function median(values) {
  if (!values.length) return NaN;
  const sorted = [...values].sort((a, b) => a - b);
  return sorted[Math.floor(sorted.length / 2)];
}

function onMessage(text) {
  let reply;
  try {
    reply = JSON.parse(text);
  } catch (error) {  // cannot happen with this server (it sends strict JSON); never wait for ever if it does
    play.pending.clear();
    sayError(new Error(`the server sent a play reply the page cannot read: ${error.message}`));
    return;
  }
  if (reply.type === "progress") {
    const waiting = play.pending.get(reply.seq);
    if (waiting) waiting.progress = reply;
    return;
  }
  onReply(reply);
}

function onReply(reply) {
  const sent = play.pending.get(reply.seq);
  play.pending.delete(reply.seq);
  if (reply.type === "error") {
    sayError(new Error(reply.message));
    return;
  }
  if (reply.seq !== null && reply.seq !== undefined && reply.seq < play.loadSeq) return;  // the previous level's
  if (sent !== undefined && reply.type === "state" && sent.type === "step") {
    play.rtts.push(performance.now() - sent.sent);
    play.stepMs.push(reply.step_ms);
    if (play.rtts.length > 300) { play.rtts.shift(); play.stepMs.shift(); }
  }
  if (reply.level) {
    play.period = 1000 * (reply.level.seconds_per_step || 1 / 30);
    play.controls = reply.controls;
    play.agent = reply.agent;
    play.running = true;
    play.steps = 0;
    play.episodes = 0;
    play.nextStep = performance.now() + play.period;
    renderKeys();
    say(`playing ${play.title}${reply.agent ? " with agent " + reply.agent : ""}`, "ok");
  } else if (reply.type === "agent") {
    play.agent = reply.agent;
  }
  if (reply.type !== "state") return;
  play.frame = reply;
  if (sent !== undefined && sent.type === "step") play.steps += 1;
  if (reply.done) {
    play.lastOutcome = reply.outcome;
    play.episodes += 1;
    const how = `episode ${play.episodes} ended: ${reply.outcome}, return ${reply.return.toFixed(3)}`;
    if (play.agentDrives && play.agent) {  // watching: the next episode (the engine's auto-reset) goes on
      say(`${how}; the agent plays on (untick "agent drives" to take over)`, reply.outcome === "solved" ? "ok" : "bad");
    } else {
      play.running = false;
      say(`${how}; press R or Reset to play again`, reply.outcome === "solved" ? "ok" : "bad");
    }
  }
  renderStats();
  if (play.speed === "max" && sent !== undefined && sent.type === "step") maybeStep(performance.now());
}

// What the page waits for, once a reply is over WAIT_SHOWN_AFTER_MS late: the server's own word when it sent one
// ("compiling the agent's policy for size S (first use)"), else the request it waits on.
function renderWait(now) {
  let oldest = null;
  for (const waiting of play.pending.values()) if (!oldest || waiting.sent < oldest.sent) oldest = waiting;
  const box = document.getElementById("play-wait");
  let text = "";
  if (play.opening) {
    text = "opening the play connection ...";
  } else if (oldest && now - oldest.sent > WAIT_SHOWN_AFTER_MS) {
    const waited = seconds(now - oldest.sent);
    const names = { load: "loading the level", agent: "loading the agent", reset: "resetting", step: "the step" };
    if (oldest.progress) {
      text = `${oldest.progress.what} ... ${waited}`;
    } else if (now - oldest.sent > 3 * WAIT_SHOWN_AFTER_MS) {
      text = `waiting for the server's reply to ${names[oldest.type] || oldest.type}, no word from it for ${waited}`;
    } else {
      text = `waiting for ${names[oldest.type] || oldest.type} ... ${waited}`;
    }
  }
  if (text !== play.waitShown) {
    box.textContent = text;
    box.hidden = !text;
    play.waitShown = text;
    const what = text.replace(/ [0-9]+ s$/, "");  // what the page waited for, newest last (tests, the console)
    if (what && what !== play.waits[play.waits.length - 1]) {
      play.waits.push(what);
      if (play.waits.length > 100) play.waits.shift();
    }
  }
}

function renderStats() {
  const f = play.frame;
  if (!f) return;
  document.getElementById("stat-t").textContent = f.t;
  document.getElementById("stat-steps").textContent = play.steps;
  document.getElementById("stat-episodes").textContent = play.episodes;
  document.getElementById("stat-reward").textContent = f.reward.toFixed(4);
  document.getElementById("stat-return").textContent = f.return.toFixed(4);
  document.getElementById("stat-outcome").textContent = play.lastOutcome || (play.running ? "playing" : "paused");
  document.getElementById("stat-step-ms").textContent =
    `${f.step_ms.toFixed(2)} ms (median ${median(play.stepMs).toFixed(2)})`;
  document.getElementById("stat-rtt-ms").textContent =
    play.rtts.length ? `${play.rtts[play.rtts.length - 1].toFixed(1)} ms (median ${median(play.rtts).toFixed(1)})` : "-";
  document.getElementById("stat-driver").textContent = play.agentDrives && play.agent ? `agent ${play.agent}` : "you";
}

function renderKeys() {
  const box = document.getElementById("play-keys");
  const used = new Set([...play.controls.motors, ...play.controls.thrusters.map((t) => 4 + t)]);
  box.innerHTML = "<div>Keys (R reset, P pause):</div>";
  for (const [what, keys, dim] of KEY_HELP) {
    const line = document.createElement("div");
    line.innerHTML = `<kbd></kbd> ${what}${used.has(dim) ? "" : " (unused here)"}`;
    line.querySelector("kbd").textContent = keys;
    line.dataset.dim = dim;
    box.appendChild(line);
  }
}

function currentAction() {
  const action = [0, 0, 0, 0, 0, 0];
  for (const code of play.held) {
    const [dim, value] = KEYS[code];
    action[dim] = value;
  }
  return action;
}

async function sendWhenOpen(message) {
  try {
    await connect();
    send(message);
  } catch (error) {
    sayError(error);
  }
}

async function openInPlay(source, title) {
  play.source = source;
  play.title = title || `${source.set} / ${source.name}`;
  play.lastOutcome = null;
  play.frame = null;
  play.running = false;
  play.rtts = [];
  play.stepMs = [];
  document.getElementById("play-title").textContent = play.title;
  show("play");
  await sendWhenOpen({ type: "load", ...source });
}

function resetPlay() {
  if (!play.ready || !play.source) return;
  play.lastOutcome = null;
  play.running = true;
  play.nextStep = performance.now() + play.period;
  send({ type: "reset" });
}

// The next step, when one is due and none is outstanding. Called at every animation frame, and, at "as fast as it
// goes", as soon as a step's reply is in (the display's frame rate would otherwise cap the steps at one a frame).
function maybeStep(now) {
  if (studio.page !== "play" || !play.ready || !play.running || play.pending.size || !play.frame) return;
  if (now < play.nextStep) return;
  const message = play.agentDrives && play.agent ? { type: "step", agent: true } : { type: "step", action: currentAction() };
  send(message);
  // Real time (speed 1): one agent step per frame_skip * dt of wall clock; never more than one step behind.
  const period = play.speed === "max" ? 0 : play.period / play.speed;
  play.nextStep = Math.max(play.nextStep + period, now - period);
}

function tick(now) {
  if (studio.page === "play") {
    maybeStep(now);
    renderWait(now);
    drawScene(document.getElementById("play-canvas"), play.frame ? play.frame.scene : null);
  }
  requestAnimationFrame(tick);
}

async function loadAgents() {
  try {
    const data = await api("/api/agents");
    for (const id of ["play-agent", "gallery-agent"]) {
      for (const checkpoint of data.checkpoints) {
        const option = document.createElement("option");
        option.value = checkpoint;
        option.textContent = checkpoint;
        document.getElementById(id).appendChild(option);
      }
    }
    document.getElementById("gallery-agent").disabled = !data.enabled;
    document.getElementById("gallery-rates").disabled = !data.enabled;
    if (!data.enabled) {
      for (const id of ["play-agent", "play-checkpoint", "play-load-agent", "play-agent-drives"]) {
        document.getElementById(id).disabled = true;
      }
    }
    const send = document.getElementById("editor-send");
    send.hidden = !data.inject_run;
    if (data.inject_run) send.textContent = `Send to run ${data.inject_run}`;
    setupCurriculum(data.inject_run);
  } catch (error) {
    sayError(error);
  }
}

function setupPlay() {
  document.getElementById("play-reset").addEventListener("click", resetPlay);
  document.getElementById("play-pause").addEventListener("click", () => {
    play.running = !play.running;
    play.nextStep = performance.now();
    renderStats();
  });
  document.getElementById("play-load-agent").addEventListener("click", async () => {
    const typed = document.getElementById("play-checkpoint").value.trim();
    const chosen = typed || document.getElementById("play-agent").value || null;
    say(chosen ? `loading agent ${chosen} ...` : "agent unloaded", "ok");
    await sendWhenOpen({ type: "agent", checkpoint: chosen });
  });
  document.getElementById("play-speed").addEventListener("change", (event) => {
    play.speed = event.target.value === "max" ? "max" : Number(event.target.value);
    play.nextStep = performance.now();
  });
  document.getElementById("play-agent-drives").addEventListener("change", (event) => {
    play.agentDrives = event.target.checked;
    renderStats();
  });
  window.addEventListener("keydown", (event) => {
    if (studio.page === "play" && event.target.tagName !== "INPUT") {
      if (event.code in KEYS) {
        play.held.add(event.code);
        event.preventDefault();
      } else if (event.code === "KeyR") {
        resetPlay();
      } else if (event.code === "KeyP") {
        document.getElementById("play-pause").click();
      }
    } else if (studio.page === "editor" && event.target.tagName !== "INPUT") {
      if ((event.ctrlKey || event.metaKey) && event.code === "KeyZ") {
        if (event.shiftKey) undoRedo(editor.redo, editor.undo); else undoRedo(editor.undo, editor.redo);
        event.preventDefault();
      } else if ((event.ctrlKey || event.metaKey) && event.code === "KeyY") {
        undoRedo(editor.redo, editor.undo);
        event.preventDefault();
      } else if ((event.code === "Delete" || event.code === "Backspace") && editor.selected !== null) {
        edit([{ op: "delete", body: editor.selected }]);
      }
    }
  });
  window.addEventListener("keyup", (event) => play.held.delete(event.code));
  window.addEventListener("blur", () => play.held.clear());
}

// ---------------------------------------------------------------------------------------------------------------
// Charts (uPlot, static/vendor/). `plot` draws into a figure's div, making the chart anew only when its series
// change, else giving it the new data; every chart is kept in `studio.charts` by its div's id.

const charts = {};
studio.charts = charts;
const CHART_HEIGHT = 220;
const COLOURS = ["#3e7bfa", "#e8590c", "#2b8a3e", "#ae3ec9", "#c92a2a", "#1098ad", "#5c940d", "#862e9c", "#d9480f",
  "#364fc7"];

function plot(id, options, data) {
  const element = document.getElementById(id);
  const width = Math.max(320, element.clientWidth || element.parentElement.clientWidth || 520);
  const signature = JSON.stringify(options.series.map((series) => series.label)) + width;
  const chart = charts[id];
  if (chart && chart.signature === signature) {
    chart.setData(data);
    return chart;
  }
  if (chart) chart.destroy();
  element.replaceChildren();
  const made = new uPlot({ width, height: CHART_HEIGHT, legend: { live: false }, ...options }, data, element);
  made.signature = signature;
  charts[id] = made;
  return made;
}

// [lo, hi] widened by 5% each side, or by one half when it is a single value.
function padded(lo, hi) {
  const pad = hi > lo ? 0.05 * (hi - lo) : Math.max(0.5, Math.abs(lo) * 0.05);
  return [lo - pad, hi + pad];
}

function pointsOnly(label, colour, size) {
  return { label, stroke: colour, fill: colour, paths: () => null, points: { show: true, space: 0, size, fill: colour } };
}

// ---------------------------------------------------------------------------------------------------------------
// Curriculum: the running run's buffer, its charts and knobs (GET /api/curriculum, POST /api/curriculum/knobs)

const curriculum = { run: null, knobs: {}, timer: null, report: null, loading: false, refreshWanted: false, note: null,
  histRange: [0, 1] };
studio.curriculum = curriculum;
const CURRICULUM_EVERY_MS = 5000;

// The buffer statistics shown above the table (`curriculum.stats.buffer_summary` has more: `impulse curriculum
// inspect` prints them all).
const SUMMARY_FIELDS = ["buffer_size", "buffer_fill", "count_inserted", "count_evicted", "count_rejected",
  "count_replay_batches", "score_mean", "score_max", "age_mean"];

const KNOB_CHOICES = {
  score: ["maxmc", "pvl", "l1_value_loss", "learnability"],
  prioritization: ["rank", "power"],
};

function fixed(value, digits) {
  return value === null || value === undefined ? "-" : Number(value).toFixed(digits);
}

// A count that need not be whole (episodes are decayed by score_memory): whole numbers as they are, others to one
// decimal.
function count(value) {
  if (value === null || value === undefined) return "-";
  return Number.isInteger(value) ? String(value) : Number(value).toFixed(1);
}

// `resetKnobs`: the knob fields show the service's values again, even those typed into (the Refresh button);
// the timer's refreshes leave a field being typed into, or typed into and not applied, as it is.
async function loadCurriculum(resetKnobs) {
  if (!curriculum.run) return;
  if (curriculum.loading) {  // one request at a time; a Refresh pressed meanwhile asks again when it is answered
    if (resetKnobs === true) curriculum.refreshWanted = true;
    return;
  }
  const top = Number(document.getElementById("curriculum-top").value) || 24;
  curriculum.loading = true;
  curriculum.note = curriculum.note || waitNote(document.getElementById("curriculum-status"));
  if (!curriculum.report) curriculum.note.start("loading the run's curriculum ...");
  else curriculum.note.start("asking the run's curriculum ...");
  try {
    const report = await api(`/api/curriculum?top=${top}`);
    curriculum.report = report;
    curriculum.note.stop(`read ${new Date().toLocaleTimeString()}`);
    renderCurriculum(report, resetKnobs === true);
  } catch (error) {
    curriculum.note.stop("the run's curriculum did not answer");
    sayError(error);
  } finally {
    curriculum.loading = false;
    if (curriculum.refreshWanted) {
      curriculum.refreshWanted = false;
      loadCurriculum(true);
    }
  }
}

function renderCurriculum(report, resetKnobs) {
  const summary = report.summary || {};
  const shown = SUMMARY_FIELDS.filter((k) => typeof summary[k] === "number").map((k) =>
    `${k.replace(/_/g, " ")} ${Number.isInteger(summary[k]) ? summary[k] : summary[k].toFixed(3)}`);
  document.getElementById("curriculum-summary").textContent =
    [`${report.method}`, `policy version ${report.policy_version}`, ...shown].join(" \u00b7 ");
  const body = document.querySelector("#curriculum-table tbody");
  body.replaceChildren();
  report.top.forEach((row, rank) => {
    const tr = document.createElement("tr");
    tr.dataset.levelId = row.level_id;
    if (row.origin === "injected") tr.classList.add("injected");
    const cells = [rank + 1, null, row.level_id, fixed(row.score, 4), fixed(row.solve_rate, 2), count(row.episodes),
      count(row.staleness), count(row.age), count(row.replays), fixed(row.p_replay, 4), row.origin,
      `${row.shapes} / ${row.joints} / ${row.thrusters}`];
    cells.forEach((value, i) => {
      const td = document.createElement("td");
      if (i === 1) {
        const img = document.createElement("img");
        img.alt = `level ${row.level_id}`;
        img.src = `/api/curriculum/thumbnail?level_id=${row.level_id}`;
        td.appendChild(img);
      } else {
        td.textContent = value;
        if (i === 2) td.className = "id";
        if (i === 10) td.className = "origin";
      }
      tr.appendChild(td);
    });
    body.appendChild(tr);
  });
  curriculum.knobs = report.knobs;
  renderKnobs(resetKnobs);
  renderCurriculumCharts(report);
}

function renderCurriculumCharts(report) {
  const histogram = (report.histograms || {}).score || { edges: [], counts: [] };
  const edges = histogram.edges.length ? histogram.edges : [0, 1];
  const centres = histogram.counts.map((_, i) => (edges[i] + edges[i + 1]) / 2);
  curriculum.histRange = [edges[0], edges[edges.length - 1]];
  plot("chart-histogram", {
    scales: { x: { time: false, range: () => curriculum.histRange }, y: { range: (u, lo, hi) => [0, Math.max(1, hi)] } },
    axes: [{ label: "score" }, { label: "levels" }],
    series: [{ label: "score" }, { label: "levels", stroke: COLOURS[0], fill: "rgba(62,123,250,0.4)",
      paths: uPlot.paths.bars({ size: [0.92, 200] }), points: { show: false } }],
  }, [centres, histogram.counts]);

  // One point per buffered level, sorted by score (uPlot's x is ascending); levels this studio sent in are a
  // series of their own, and levels with no episode yet are drawn just below 0.
  const points = report.points || { score: [], solve_rate: [], origin: [] };
  const order = points.score.map((_, i) => i).filter((i) => points.score[i] !== null)
    .sort((a, b) => points.score[a] - points.score[b]);
  const UNPLAYED = -0.05;
  const pick = (test) => order.map((i) => test(i) ? (points.solve_rate[i] === null ? UNPLAYED : points.solve_rate[i]) : null);
  const injected = (i) => points.origin[i] === "injected";
  const scores = order.map((i) => points.score[i]);
  // From the data, not uPlot's: it widens a single value to 0 to 100 before a range function sees it.
  curriculum.scoreRange = scores.length ? padded(scores[0], scores[scores.length - 1]) : [0, 1];
  plot("chart-scatter", {
    scales: { x: { time: false, range: () => curriculum.scoreRange }, y: { range: [-0.1, 1.05] } },
    axes: [{ label: "score" }, { label: "solve rate" }],
    series: [{ label: "score" },
      pointsOnly("levels", COLOURS[0], 5),
      pointsOnly("injected", "#ff7800", 10),
      pointsOnly("no episode yet (at -0.05)", "#999", 5)],
  }, [scores,
    pick((i) => !injected(i) && points.solve_rate[i] !== null),
    pick(injected),
    pick((i) => !injected(i) && points.solve_rate[i] === null)]);

  // The studio's samples of the buffer's counters (one per answer it got), and the levels it sent in.
  const history = report.history || [];
  const injections = report.injections || [];
  const series = [["count_inserted", "inserted"], ["count_evicted", "evicted"], ["count_replay_batches", "replay batches"],
    ["count_rejected", "rejected"]];
  // The x range takes in the injections too, so a level sent in before the first sample still shows.
  const times = [...history.map((sample) => sample.t), ...injections.map((injection) => injection.t)];
  curriculum.timeRange = times.length ? padded(Math.min(...times), Math.max(...times)) : [0, 1];
  plot("chart-history", {
    scales: { x: { time: true, range: () => curriculum.timeRange } },
    axes: [{}, { label: "count since the run began" }],
    series: [{ label: "time" }, ...series.map(([, label], i) => ({ label, stroke: COLOURS[i], width: 2,
      points: { show: true, size: 5 } }))],
    hooks: { draw: [(u) => {
      const ctx = u.ctx;
      ctx.save();
      ctx.strokeStyle = "#ff7800";
      ctx.lineWidth = 2 * devicePixelRatio;
      ctx.setLineDash([6 * devicePixelRatio, 4 * devicePixelRatio]);
      for (const injection of injections) {
        const x = u.valToPos(injection.t, "x", true);
        if (x < u.bbox.left || x > u.bbox.left + u.bbox.width) continue;
        ctx.beginPath();
        ctx.moveTo(x, u.bbox.top);
        ctx.lineTo(x, u.bbox.top + u.bbox.height);
        ctx.stroke();
      }
      ctx.restore();
    }] },
  }, [history.map((sample) => sample.t), ...series.map(([name]) => history.map((sample) => sample[name]))]);
}

function renderKnobs(reset) {
  const table = document.getElementById("curriculum-knobs");
  const names = Object.keys(curriculum.knobs);
  const existing = [...table.querySelectorAll("[data-knob]")].map((input) => input.dataset.knob);
  if (JSON.stringify(existing) === JSON.stringify(names)) {
    for (const input of table.querySelectorAll("[data-knob]")) {
      const untouched = !input.dataset.dirty && document.activeElement !== input;
      if (reset || untouched) {
        input.value = String(curriculum.knobs[input.dataset.knob]);
        delete input.dataset.dirty;
      }
    }
    return;
  }
  table.replaceChildren();
  for (const [name, value] of Object.entries(curriculum.knobs)) {
    const tr = document.createElement("tr");
    const label = document.createElement("td");
    label.textContent = name;
    const cell = document.createElement("td");
    let input;
    if (name in KNOB_CHOICES) {
      input = document.createElement("select");
      for (const choice of KNOB_CHOICES[name]) {
        const option = document.createElement("option");
        option.value = option.textContent = choice;
        input.appendChild(option);
      }
    } else if (typeof value === "boolean") {
      input = document.createElement("select");
      for (const choice of ["true", "false"]) {
        const option = document.createElement("option");
        option.value = option.textContent = choice;
        input.appendChild(option);
      }
    } else {
      input = document.createElement("input");
      input.type = "number";
      input.step = "any";
    }
    input.value = String(value);
    input.dataset.knob = name;
    input.id = `knob-${name}`;
    input.addEventListener("input", () => { input.dataset.dirty = "1"; });
    input.addEventListener("change", () => { input.dataset.dirty = "1"; });
    cell.appendChild(input);
    tr.append(label, cell);
    table.appendChild(tr);
  }
}

async function applyKnobs() {
  const changes = [];
  for (const input of document.querySelectorAll("#curriculum-knobs [data-knob]")) {
    const name = input.dataset.knob;
    if (input.value !== String(curriculum.knobs[name])) changes.push(`${name}=${input.value}`);
  }
  if (!changes.length) {
    say("no knob changed", "ok");
    return;
  }
  say(`sending ${changes.join(", ")} ...`, "ok");
  try {
    const reply = await waitingFor(`sending ${changes.join(", ")}`, api("/api/curriculum/knobs", { set: changes }));
    curriculum.knobs = reply.knobs || curriculum.knobs;
    const changed = Object.entries(reply.changed || {}).map(([k, [a, b]]) => `${k}: ${a} -> ${b}`);
    say(changed.length ? `changed ${changed.join(", ")}` : "nothing changed", "ok");
    renderKnobs(true);
  } catch (error) {
    say("the knobs were not changed", "ok");
    sayError(error);
  }
}

function setupCurriculum(run) {
  curriculum.run = run;
  document.getElementById("tab-curriculum").hidden = !run;
  if (!run) return;
  document.getElementById("curriculum-title").textContent = `run ${run}`;
  document.getElementById("curriculum-refresh").addEventListener("click", () => loadCurriculum(true));
  document.getElementById("curriculum-apply").addEventListener("click", applyKnobs);
  const every = () => {
    clearInterval(curriculum.timer);
    curriculum.timer = document.getElementById("curriculum-auto").checked ? setInterval(() => {
      if (studio.page === "curriculum") loadCurriculum();
    }, CURRICULUM_EVERY_MS) : null;
  };
  document.getElementById("curriculum-auto").addEventListener("change", every);
  every();
  document.getElementById("tab-curriculum").addEventListener("click", () => loadCurriculum());
}

// ---------------------------------------------------------------------------------------------------------------
// Run: a run's learning curves from its metrics.jsonl (GET /api/runs, GET /api/run/metrics?run=R&after=U), asked
// for again every RUN_EVERY_MS while the page is shown and "live" is ticked; each answer adds the rows after the
// last update the page has.

const RUN_EVERY_MS = 3000;
const RUN_CHARTS = [
  { id: "solve", title: "solve rate (training episodes; eval/mean: the evaluation)", columns: ["solve_rate", "eval/mean"] },
  { id: "return", title: "episode return", columns: ["episode_return"] },
  { id: "losses", title: "losses", columns: ["policy_loss", "value_loss", "total_loss"] },
  { id: "entropy", title: "entropy and KL", columns: ["entropy", "approx_kl"] },
  { id: "lag", title: "policy lag (updates between acting and learning)", columns: ["policy_lag"] },
  { id: "eval", title: "evaluation groups (eval/...: solve rate per group)",
    columns: (names) => names.filter((n) => n.startsWith("eval/") && !["eval/policy_version", "eval/skipped"].includes(n)) },
  { id: "speed", title: "environment steps per second", columns: ["steps_per_s"] },
];
const run = { id: null, columns: [], data: {}, rows: 0, last: null, timer: null, loadingFor: null, note: null, listed: [] };
studio.run = run;

async function loadRuns() {
  try {
    const { runs, selected } = await api("/api/runs");
    run.listed = runs;
    const select = document.getElementById("run-select");
    const keep = run.id && runs.some((r) => r.id === run.id) ? run.id : selected;
    select.replaceChildren(...runs.map((r) => {
      const option = document.createElement("option");
      option.value = r.id;
      option.textContent = `${r.title} (${r.file})`;
      return option;
    }));
    if (!runs.length) document.getElementById("run-status").textContent =
      "no runs found: start the studio with --run RUN_DIR, or train into ./runs";
    if (keep) {
      select.value = keep;
      if (keep !== run.id) chooseRun(keep);
    }
  } catch (error) {
    sayError(error);
  }
}

function chooseRun(id) {
  run.id = id;
  run.columns = [];
  run.data = {};
  run.rows = 0;
  run.last = null;
  for (const key of Object.keys(charts)) if (key.startsWith("run-chart-")) { charts[key].destroy(); delete charts[key]; }
  document.getElementById("run-charts").replaceChildren();
  fetchRunRows(true);
}

async function fetchRunRows(first) {
  if (!run.id || run.loadingFor === run.id) return;
  const id = run.id;
  run.loadingFor = id;
  run.note = run.note || waitNote(document.getElementById("run-status"));
  if (first) run.note.start(`reading ${id} ...`);
  try {
    for (;;) {
      const query = new URLSearchParams({ run: id });
      if (run.last !== null) query.set("after", run.last);
      const reply = await api(`/api/run/metrics?${query}`);
      if (run.id !== id) return;
      if (reply.total < run.rows) {  // the file was rewritten (a resumed run set rows aside): read it again
        run.columns = []; run.data = {}; run.rows = 0; run.last = null;
        continue;
      }
      addRunRows(reply);
      if (!reply.more || !reply.rows.length) break;
    }
    run.note.stop(`${run.rows} rows, last update ${run.last === null ? "-" : run.last} \u00b7 read ` +
      `${new Date().toLocaleTimeString()}`);
    renderRunCharts();
  } catch (error) {
    if (run.id === id) run.note.stop(`could not read ${id}`);
    sayError(error);
  } finally {
    if (run.loadingFor === id) run.loadingFor = null;
  }
}

function addRunRows(reply) {
  for (const name of reply.columns) {
    if (!(name in run.data)) {
      run.data[name] = new Array(run.rows).fill(null);
      run.columns.push(name);
    }
  }
  for (const row of reply.rows) {
    const values = Object.fromEntries(reply.columns.map((name, i) => [name, row[i]]));
    for (const name of run.columns) run.data[name].push(name in values ? values[name] : null);
  }
  run.rows += reply.rows.length;
  if (reply.rows.length) run.last = reply.last_update;
}

function renderRunCharts() {
  const container = document.getElementById("run-charts");
  const chosen = document.getElementById("run-x").value;  // env steps only when every row has them
  const xName = chosen in run.data && !run.data[chosen].includes(null) ? chosen : "update";
  const xs = run.data[xName] || [];
  for (const chart of RUN_CHARTS) {
    const columns = (typeof chart.columns === "function" ? chart.columns(run.columns) : chart.columns)
      .filter((name) => name in run.data);
    const id = `run-chart-${chart.id}`;
    let figure = document.getElementById(`${id}-figure`);
    if (!columns.length) {
      if (figure) figure.hidden = true;
      continue;
    }
    if (!figure) {
      figure = document.createElement("figure");
      figure.id = `${id}-figure`;
      figure.innerHTML = `<figcaption></figcaption><div id="${id}"></div>`;
      figure.querySelector("figcaption").textContent = chart.title;
      container.appendChild(figure);
    }
    figure.hidden = false;
    plot(id, {
      scales: { x: { time: false } },
      axes: [{ label: xName.replace("_", " ") }, {}],
      series: [{ label: xName }, ...columns.map((name, i) => ({ label: name, stroke: COLOURS[i % COLOURS.length],
        width: 1.5, spanGaps: true, points: { show: false } }))],
    }, [xs, ...columns.map((name) => run.data[name])]);
  }
}

function showRunPage() {
  if (!run.listed.length || !run.id) loadRuns(); else fetchRunRows();
}

function setupRun() {
  document.getElementById("run-select").addEventListener("change", (event) => chooseRun(event.target.value));
  document.getElementById("run-rescan").addEventListener("click", loadRuns);
  document.getElementById("run-x").addEventListener("change", () => {
    for (const key of Object.keys(charts)) if (key.startsWith("run-chart-")) { charts[key].destroy(); delete charts[key]; }
    renderRunCharts();
  });
  run.timer = setInterval(() => {
    if (studio.page === "run" && document.getElementById("run-live").checked) fetchRunRows();
  }, RUN_EVERY_MS);
}

// ---------------------------------------------------------------------------------------------------------------

function setup() {
  for (const tab of document.querySelectorAll(".tab")) tab.addEventListener("click", () => show(tab.dataset.page));
  document.getElementById("alert-close").addEventListener("click", dismissAlert);
  document.getElementById("gallery-set").addEventListener("change", (event) => loadGallery(event.target.value));
  document.getElementById("gallery-filter").addEventListener("input", renderGallery);
  document.getElementById("gallery-rates").addEventListener("click", loadSolveRates);
  setupEditor();
  setupPlay();
  setupRun();
  show("gallery");
  renderEditor();
  renderKeys();
  requestAnimationFrame(tick);
  loadSets().catch(sayError);
  loadAgents();
}

setup();
