// The DFD handles page: every interaction is sent to the server (JSON), which deforms the mesh, renders it and
// answers with its state; the page then shows the new image and draws the handle / anchor markers on top.
// Requests run one at a time, in order (a promise chain), and drag motion is coalesced: while one step is in
// flight the cursor's further motion accumulates and goes out as the next step.
"use strict";

const $ = (id) => document.getElementById(id);
const img = $("mesh");
const overlay = $("overlay");
const ctx = overlay.getContext("2d");

const S = {
  info: null,
  state: null,
  shown: -1, // version of the displayed image
  shownKind: "", // "png" (lossless, full resolution) or "jpg/<scale>" (a drag frame)
  slow: false, // full-resolution frames took too long: half resolution while dragging
  pending: 0, // requests queued or running
  chain: Promise.resolve(),
  drag: null, // {mode, handle, sent: [x, y], to: [x, y]}
  cursor: null,
};

function enqueue(task) {
  S.pending += 1;
  const run = S.chain.then(task).catch(showError).finally(() => { S.pending -= 1; });
  S.chain = run;
  return run;
}

// True when nothing is queued or in flight and the displayed image is the latest state's (used by tests).
window.dfdIdle = () => S.pending === 0 && S.drag === null && S.state !== null && S.shown === S.state.version &&
  S.shownKind === "png";

async function api(path, body) {
  const init = body === undefined ? {} : {
    method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
  };
  const response = await fetch(path, init);
  const data = await response.json();
  if (!response.ok) throw new Error(data.error || response.statusText);
  return data;
}

function showError(err) {
  const s = $("status");
  s.textContent = String(err.message || err);
  s.className = "error";
}

// Show a state: its image, then the markers. Drag frames are JPEG (fast to encode), at half resolution when
// full-resolution frames take too long; at rest the image is the lossless full-resolution PNG.
async function show(state, dragFrame = false) {
  S.state = state;
  const scale = dragFrame && S.slow ? 2 : 1;
  const kind = dragFrame ? `jpg/${scale}` : "png";
  if (state.version !== S.shown || kind !== S.shownKind) {
    const t0 = performance.now();
    img.src = dragFrame ? `/api/image.jpg?v=${state.version}&scale=${scale}` : `/api/image.png?v=${state.version}`;
    await img.decode();
    S.shown = state.version;
    S.shownKind = kind;
    const ms = performance.now() - t0;
    if (kind === "jpg/1") S.slow = ms > 100;
    if (scale === 1) S.imageMs = ms;
  }
  drawOverlay();
  updatePanel();
}

function drawOverlay() {
  const st = S.state;
  ctx.clearRect(0, 0, overlay.width, overlay.height);
  if (!st) return;
  for (const m of st.markers) {
    ctx.beginPath();
    if (m.kind === "anchor") {
      ctx.rect(m.x - 5, m.y - 5, 10, 10);
      ctx.fillStyle = "#1f6feb";
    } else {
      ctx.arc(m.x, m.y, 6, 0, 2 * Math.PI);
      ctx.fillStyle = "#e4572e";
    }
    ctx.fill();
    ctx.lineWidth = 2;
    ctx.strokeStyle = "#fff";
    ctx.stroke();
    if (m.kind === "handle" && m.index === st.selected) {
      ctx.beginPath();
      ctx.arc(m.x, m.y, 10, 0, 2 * Math.PI);
      ctx.strokeStyle = "#f5b700";
      ctx.stroke();
      if (S.drag && S.drag.mode === "rotate" && S.cursor) {
        ctx.beginPath();
        ctx.moveTo(m.x, m.y);
        ctx.lineTo(S.cursor[0], S.cursor[1]);
        ctx.setLineDash([4, 4]);
        ctx.stroke();
        ctx.setLineDash([]);
      }
    }
  }
}

function updatePanel() {
  const st = S.state;
  const o = st.options;
  $("locality").checked = o.locality;
  if (document.activeElement !== $("lambda")) $("lambda").value = o.lambda;
  $("symmetric").checked = o.symmetric;
  $("symmetric").disabled = !S.info.symmetry_available;
  $("pou").checked = o.pou;
  $("show-weights").checked = o.show_weights;
  const p = st.symmetry_plane;
  $("plane").textContent = p
    ? `(n = ${p.normal.map((x) => x.toFixed(2)).join(", ")}, score ${p.score.toFixed(3)})`
    : (S.info.field_given ? "(no plane found)" : "(needs --field)");
  const list = $("handles");
  list.textContent = "";
  st.handles.forEach((v, k) => {
    const t = st.transforms[k];
    const li = document.createElement("li");
    li.textContent = `#${k} vertex ${v}  t = (${t.map((r) => r[3].toFixed(3)).join(", ")})`;
    if (k === st.selected) li.className = "selected";
    li.onclick = () => enqueue(async () => show(await api("/api/handle", { action: "select", handle: k })));
    list.appendChild(li);
  });
  const s = $("status");
  s.className = "";
  s.textContent = `${S.info.n_vertices} vertices, ${st.handles.length} handle(s), ${st.anchors.length} anchor(s)`;
  const t = st.timings;
  const f = (x) => (x === undefined ? "-" : x.toFixed(1));
  $("timings").textContent = `server: deform ${f(t.deform_ms)} ms, render ${f(t.render_ms)} ms, ` +
    `png ${f(t.png_ms)} ms, jpeg ${f(t.jpeg_ms)} ms; last image round trip ${f(S.imageMs)} ms` +
    (S.slow ? " (half-resolution frames while dragging)" : "");
}

// Display pixel coordinates of a pointer event (the image may be shown scaled).
function position(e) {
  const r = overlay.getBoundingClientRect();
  return [(e.clientX - r.left) * (overlay.width / r.width), (e.clientY - r.top) * (overlay.height / r.height)];
}

function pump() {
  enqueue(async () => {
    const d = S.drag;
    while (d && d.mode && (d.to[0] !== d.sent[0] || d.to[1] !== d.sent[1])) {
      const from = d.sent;
      const to = d.to;
      d.sent = to;
      const body = { mode: d.mode, from, to };
      if (d.handle !== null) body.handle = d.handle;
      await show(await api("/api/drag", body), true);
    }
    if (d && d.released && S.drag === d) {
      S.drag = null;
      await show(S.state);
    }
  });
}

overlay.addEventListener("pointerdown", (e) => {
  e.preventDefault();
  $("view").focus();
  const p = position(e);
  const anchorMode = $("mode-anchor").checked || e.ctrlKey || e.metaKey;
  if (e.button !== 0 && e.button !== 2) return;
  if (anchorMode && e.button === 0) {
    enqueue(async () => show((await api("/api/pick", { x: p[0], y: p[1], action: "anchor" })).state));
    return;
  }
  overlay.setPointerCapture(e.pointerId);
  const d = { mode: null, handle: null, sent: p, to: p, released: false };
  S.drag = d;
  if (e.button === 2 || e.altKey) {
    d.mode = "orbit";
    return;
  }
  const rotate = e.shiftKey;
  enqueue(async () => {
    const r = await api("/api/pick", { x: p[0], y: p[1], action: rotate ? "rotate" : "handle" });
    if (r.handle === null) {
      d.mode = "orbit";
    } else {
      d.mode = rotate ? "rotate" : "translate";
      d.handle = r.handle;
    }
    await show(r.state, true);
  });
  pump();
});

overlay.addEventListener("pointermove", (e) => {
  S.cursor = position(e);
  if (!S.drag || S.drag.released) return;
  S.drag.to = S.cursor;
  pump();
});

function release(e) {
  if (!S.drag || S.drag.released) return;
  if (e.type === "pointerup") S.drag.to = position(e);
  S.drag.released = true;
  pump();
}
overlay.addEventListener("pointerup", release);
overlay.addEventListener("pointercancel", release);
overlay.addEventListener("contextmenu", (e) => e.preventDefault());

let zoom = 1;
overlay.addEventListener("wheel", (e) => {
  e.preventDefault();
  zoom *= Math.exp(0.001 * e.deltaY);
  enqueue(async () => {
    if (zoom === 1) return;
    const factor = zoom;
    zoom = 1;
    await show(await api("/api/view", { zoom: factor }));
  });
}, { passive: false });

function setOption(body) {
  enqueue(async () => show(await api("/api/options", body)));
}
$("locality").addEventListener("change", (e) => setOption({ locality: e.target.checked }));
$("symmetric").addEventListener("change", (e) => setOption({ symmetric: e.target.checked }));
$("pou").addEventListener("change", (e) => setOption({ pou: e.target.checked }));
$("show-weights").addEventListener("change", (e) => setOption({ show_weights: e.target.checked }));
$("lambda").addEventListener("change", (e) => {
  const lam = Number(e.target.value);
  if (e.target.value !== "" && Number.isFinite(lam)) setOption({ lambda: lam });
});

function selectedAction(action) {
  enqueue(async () => {
    if (S.state.selected === null) throw new Error("no handle is selected.");
    await show(await api("/api/handle", { action, handle: S.state.selected }));
  });
}
$("reset-handle").onclick = () => selectedAction("reset");
$("remove-handle").onclick = () => selectedAction("remove");
$("reset-transforms").onclick = () => enqueue(async () => show(await api("/api/reset", { what: "transforms" })));
$("clear-all").onclick = () => enqueue(async () => show(await api("/api/reset", { what: "all" })));
$("reset-view").onclick = () => enqueue(async () => show(await api("/api/reset", { what: "view" })));

$("view").addEventListener("keydown", (e) => {
  if (!S.state) return;
  if ((e.key === "Delete" || e.key === "Backspace") && S.state.selected !== null) selectedAction("remove");
  else if ((e.key === "r" || e.key === "R") && S.state.selected !== null) selectedAction("reset");
  else if (e.key === "Escape") enqueue(async () => show(await api("/api/handle", { action: "deselect" })));
});

enqueue(async () => {
  S.info = await api("/api/mesh-info");
  img.width = overlay.width = S.info.width;
  img.height = overlay.height = S.info.height;
  await show(await api("/api/state"));
});
