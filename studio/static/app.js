// Impulse Studio's page: gallery, editor and play. Plain JavaScript, no libraries, no build step.
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

function say(text, kind) {
  const box = document.getElementById("message");
  box.textContent = text;
  box.className = kind || "";
}

function sayError(error) {
  const extra = error.problems && error.problems.length ? "\n" + error.problems.join("\n") : "";
  say(error.message + extra, "error");
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

// ---------------------------------------------------------------------------------------------------------------
// Pages

const studio = { page: "gallery", sets: [], levels: [], editor: null, play: null, rates: null };
window.studio = studio; // for the browser test and for poking at the page from the console

function show(page) {
  studio.page = page;
  for (const section of document.querySelectorAll(".page")) section.classList.toggle("active", section.id === `page-${page}`);
  for (const tab of document.querySelectorAll(".tab")) tab.classList.toggle("active", tab.dataset.page === page);
}

// ----- Gallery

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

async function loadGallery(setId) {
  document.getElementById("gallery-count").textContent = "loading...";
  try {
    const data = await api(`/api/levels?set=${encodeURIComponent(setId)}`);
    studio.levels = data.levels;
    renderGallery();
  } catch (error) {
    sayError(error);
  }
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
      rate.textContent = level.name in rates.rates
        ? `agent solves ${Math.round(rates.rates[level.name] * 100)}% (${rates.attempts} attempts)`
        : `agent: ${rates.skipped[level.name] || "not scored"}`;
      card.querySelector(".meta").after(rate);
    }
    card.querySelector(".edit").addEventListener("click", (e) => { e.stopPropagation(); openInEditor(level.set, level.name); });
    card.querySelector(".play").addEventListener("click", (e) => { e.stopPropagation(); openInPlay({ set: level.set, name: level.name }); });
    card.addEventListener("click", () => openInEditor(level.set, level.name));
    grid.appendChild(card);
  }
  document.getElementById("gallery-count").textContent = `${shown.length} of ${studio.levels.length} levels`;
}

async function loadSolveRates() {
  const checkpoint = document.getElementById("gallery-agent").value;
  const setId = document.getElementById("gallery-set").value;
  if (!checkpoint) {
    studio.rates = null;
    renderGallery();
    return;
  }
  say(`scoring ${checkpoint} on ${setId} (the first time compiles) ...`, "ok");
  try {
    const query = new URLSearchParams({ set: setId, checkpoint });
    const data = await api(`/api/solve_rates?${query}`);
    studio.rates = { set: setId, ...data };
    const scored = Object.values(data.rates);
    const mean = scored.length ? scored.reduce((a, b) => a + b, 0) / scored.length : 0;
    say(`${data.agent} on ${setId}: mean solve rate ${Math.round(mean * 100)}% over ${scored.length} levels`, "ok");
    renderGallery();
  } catch (error) {
    sayError(error);
  }
}

// ----- Editor

const editor = {
  doc: null, scene: null, title: "", tool: "select", role: "neutral", selected: null,
  undo: [], redo: [], drag: null, busy: false, actuators: { joints: [], thrusters: [] }, jointFrom: null,
};
studio.editor = editor;

async function openInEditor(setId, name) {
  try {
    const doc = await api(`/api/level?set=${encodeURIComponent(setId)}&name=${encodeURIComponent(name)}`);
    const state = await api("/api/edit", { level: doc, ops: [] });
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
  document.getElementById("editor-title").textContent = editor.title || "no level open";
  drawScene(document.getElementById("editor-canvas"), editor.scene, {
    selected: editor.selected, moving: editor.drag ? editor.drag.body : undefined,
    offset: editor.drag ? editor.drag.offset : [0, 0],
  });
  for (const button of document.querySelectorAll(".tool")) button.classList.toggle("active", button.dataset.tool === editor.tool);
  const shape = editor.scene && editor.selected !== null ? findShape(editor.scene, editor.selected) : null;
  const role = shape ? shape.role : editor.role;
  for (const button of document.querySelectorAll(".role")) button.classList.toggle("active", button.dataset.role === role);
  if (shape) document.getElementById("editor-fixed").checked = shape.fixed;
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
    const state = await api("/api/edit", size ? { level: editor.doc, ops, size } : { level: editor.doc, ops });
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

async function saveLevel() {
  const name = document.getElementById("editor-name").value.trim();
  if (!editor.doc) return;
  try {
    const saved = await api("/api/save", { name, level: editor.doc });
    editor.savedAs = saved.saved;
    say(`saved as ${saved.saved.set} / ${saved.saved.name} (${saved.path})`, "ok");
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
      if (editor.selected !== null) edit([{ op: "set_role", body: editor.selected, role: editor.role }]);
      else renderEditor();
    });
  }
  document.getElementById("editor-fixed").addEventListener("change", (event) => {
    if (editor.selected !== null) edit([{ op: "set_fixed", body: editor.selected, fixed: event.target.checked }]);
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
    try {
      const sent = await api("/api/inject", { level: editor.doc });
      say(`in the run's curriculum buffer: slot ${sent.slot}${sent.evicted ? " (in place of its lowest-scored level)" : ""}`, "ok");
    } catch (error) {
      sayError(error);
    }
  });
  document.getElementById("editor-play").addEventListener("click", () => {
    if (editor.doc) openInPlay({ level: editor.doc }, editor.title + " (edited)");
  });

  canvas.addEventListener("pointerdown", (event) => {
    if (!editor.scene) return;
    const point = canvasToWorld(canvas, event);
    const fixed = document.getElementById("editor-fixed").checked;
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

const play = {
  socket: null, ready: false, source: null, title: "", frame: null, held: new Set(), running: false,
  inFlight: false, nextStep: 0, period: 1000 / 30, seq: 0, sentAt: new Map(), rtts: [], stepMs: [],
  controls: { motors: [], thrusters: [] }, agentDrives: false, agent: null, queue: [],
};
studio.play = play;

function socketUrl() {
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  return `${scheme}//${location.host}/ws/play${TOKEN ? "?token=" + encodeURIComponent(TOKEN) : ""}`;
}

function connect() {
  return new Promise((resolve) => {
    if (play.socket && play.ready) { resolve(); return; }
    play.socket = new WebSocket(socketUrl());
    play.socket.addEventListener("open", () => { play.ready = true; resolve(); });
    play.socket.addEventListener("message", (event) => onReply(JSON.parse(event.data)));
    play.socket.addEventListener("close", () => {
      play.ready = false; play.inFlight = false;
      say("play connection closed; it reopens when you load a level", "error");
    });
  });
}

function send(message) {
  play.seq += 1;
  message.seq = play.seq;
  play.sentAt.set(play.seq, performance.now());
  play.inFlight = true;
  play.socket.send(JSON.stringify(message));
}

function median(values) {
  if (!values.length) return NaN;
  const sorted = [...values].sort((a, b) => a - b);
  return sorted[Math.floor(sorted.length / 2)];
}

function onReply(reply) {
  play.inFlight = false;
  const sent = play.sentAt.get(reply.seq);
  play.sentAt.delete(reply.seq);
  if (reply.type === "error") {
    sayError(new Error(reply.message));
    return;
  }
  if (sent !== undefined && reply.type === "state") {
    play.rtts.push(performance.now() - sent);
    play.stepMs.push(reply.step_ms);
    if (play.rtts.length > 300) { play.rtts.shift(); play.stepMs.shift(); }
  }
  if (reply.level) {
    play.period = 1000 * (reply.level.seconds_per_step || 1 / 30);
    play.controls = reply.controls;
    play.agent = reply.agent;
    play.running = true;
    play.nextStep = performance.now() + play.period;
    renderKeys();
    say(`playing ${play.title}${reply.agent ? " with agent " + reply.agent : ""}`, "ok");
  } else if (reply.type === "agent") {
    play.agent = reply.agent;
  }
  if (reply.type !== "state") return;
  play.frame = reply;
  if (reply.done) {
    play.lastOutcome = reply.outcome;
    play.running = false;
    say(`episode ended: ${reply.outcome}, return ${reply.return.toFixed(3)}; press R or Reset to play again`,
      reply.outcome === "solved" ? "ok" : "error");
  }
  renderStats();
}

function renderStats() {
  const f = play.frame;
  if (!f) return;
  document.getElementById("stat-t").textContent = f.t;
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

async function openInPlay(source, title) {
  play.source = source;
  play.title = title || `${source.set} / ${source.name}`;
  play.lastOutcome = null;
  play.frame = null;
  play.rtts = [];
  play.stepMs = [];
  document.getElementById("play-title").textContent = play.title;
  show("play");
  await connect();
  send({ type: "load", ...source });
}

function resetPlay() {
  if (!play.ready || !play.source) return;
  play.lastOutcome = null;
  play.running = true;
  play.nextStep = performance.now() + play.period;
  send({ type: "reset" });
}

function tick(now) {
  if (studio.page === "play") {
    if (play.ready && play.running && !play.inFlight && play.frame && now >= play.nextStep) {
      const message = play.agentDrives && play.agent ? { type: "step", agent: true } : { type: "step", action: currentAction() };
      send(message);
      // Real time: one agent step per frame_skip * dt of wall clock; never queue up more than one step behind.
      play.nextStep = Math.max(play.nextStep + play.period, now - play.period);
    }
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
    await connect();
    say(chosen ? `loading agent ${chosen} (the first time compiles its network) ...` : "agent unloaded", "ok");
    send({ type: "agent", checkpoint: chosen });
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
// Curriculum: the running run's buffer and knobs (GET /api/curriculum, POST /api/curriculum/knobs)

const curriculum = { run: null, knobs: {}, timer: null, report: null };
studio.curriculum = curriculum;

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

async function loadCurriculum() {
  if (!curriculum.run) return;
  const top = Number(document.getElementById("curriculum-top").value) || 24;
  try {
    const report = await api(`/api/curriculum?top=${top}`);
    curriculum.report = report;
    renderCurriculum(report);
  } catch (error) {
    sayError(error);
  }
}

function renderCurriculum(report) {
  const summary = report.summary || {};
  const shown = SUMMARY_FIELDS.filter((k) => typeof summary[k] === "number").map((k) =>
    `${k.replace(/_/g, " ")} ${Number.isInteger(summary[k]) ? summary[k] : summary[k].toFixed(3)}`);
  document.getElementById("curriculum-summary").textContent =
    [`${report.method}`, `policy version ${report.policy_version}`, ...shown].join(" · ");
  const body = document.querySelector("#curriculum-table tbody");
  body.replaceChildren();
  report.top.forEach((row, rank) => {
    const tr = document.createElement("tr");
    tr.dataset.levelId = row.level_id;
    const cells = [rank + 1, null, row.level_id, fixed(row.score, 4), fixed(row.solve_rate, 2), row.episodes,
      row.staleness, row.age, row.replays, fixed(row.p_replay, 4), row.origin,
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
      }
      tr.appendChild(td);
    });
    body.appendChild(tr);
  });
  curriculum.knobs = report.knobs;
  renderKnobs();
}

function renderKnobs() {
  const table = document.getElementById("curriculum-knobs");
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
  try {
    const reply = await api("/api/curriculum/knobs", { set: changes });
    curriculum.knobs = reply.knobs || curriculum.knobs;
    const changed = Object.entries(reply.changed || {}).map(([k, [a, b]]) => `${k}: ${a} -> ${b}`);
    say(changed.length ? `changed ${changed.join(", ")}` : "nothing changed", "ok");
    renderKnobs();
  } catch (error) {
    sayError(error);
  }
}

function setupCurriculum(run) {
  curriculum.run = run;
  document.getElementById("tab-curriculum").hidden = !run;
  if (!run) return;
  document.getElementById("curriculum-title").textContent = `run ${run}`;
  document.getElementById("curriculum-refresh").addEventListener("click", loadCurriculum);
  document.getElementById("curriculum-apply").addEventListener("click", applyKnobs);
  document.getElementById("curriculum-auto").addEventListener("change", (event) => {
    clearInterval(curriculum.timer);
    curriculum.timer = event.target.checked ? setInterval(() => {
      if (studio.page === "curriculum") loadCurriculum();
    }, 5000) : null;
  });
  document.getElementById("tab-curriculum").addEventListener("click", loadCurriculum);
}

// ---------------------------------------------------------------------------------------------------------------

function setup() {
  for (const tab of document.querySelectorAll(".tab")) tab.addEventListener("click", () => show(tab.dataset.page));
  document.getElementById("gallery-set").addEventListener("change", (event) => loadGallery(event.target.value));
  document.getElementById("gallery-filter").addEventListener("input", renderGallery);
  document.getElementById("gallery-rates").addEventListener("click", loadSolveRates);
  setupEditor();
  setupPlay();
  show("gallery");
  renderEditor();
  renderKeys();
  requestAnimationFrame(tick);
  loadSets().catch(sayError);
  loadAgents();
}

setup();
