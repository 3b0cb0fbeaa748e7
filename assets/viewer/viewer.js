// posefuse viewer: opens a frame JSON, sends it to this server's API and draws the answer.
// No library and no request outside this server: canvas 2D for the camera and the 3D view.

const $ = (id) => document.getElementById(id);

/** Keypoint names, skeleton edges and OKS scales, as the server defines them. */
let KP = { names: [], skeleton: [], oks_scales: [] };

/** What is on screen: the frame sent, the server's answer, and the view state. */
const state = {
  frames: [], // frames of the opened file
  source: '', // file or example name
  frame: null,
  response: null, // PoseResponse
  metrics: null, // EvaluateResponse.metrics, when the frame had ground truth
  persons: [], // one entry per answered person (see buildPersons)
  skipped: [],
  cameras: [],
  images: new Map(), // camera name -> ImageBitmap
  selected: -1, // index into persons, -1: none
  points: null, // Float32Array xyz of the points in or near a box
  pointOwner: null, // Int32Array: person index whose box holds the point, -1: only near one
  view: { yaw: Math.PI, pitch: 0.45, dist: 12, target: [0, 0, 0] },
  roundTripMs: 0,
};

const NEAR_M = 0.5; // points this far outside a box still count as "near" it

// ---------------------------------------------------------------- colours

/** A distinct colour per person (golden-angle hues), as #rrggbb. */
export function personColour(i) {
  const h = (i * 137.508 + 15) % 360;
  const s = 0.85;
  const l = 0.6;
  const f = (n) => {
    const k = (n + h / 30) % 12;
    const c = l - s * Math.min(l, 1 - l) * Math.max(-1, Math.min(k - 3, 9 - k, 1));
    return Math.round(c * 255).toString(16).padStart(2, '0');
  };
  return `#${f(0)}${f(8)}${f(4)}`;
}

// ---------------------------------------------------------------- frame adapters

/**
 * The frame's cameras, one panel each. Today a frame has one camera (`image` + `calibration`);
 * a frame with a `cameras` list (name, image, calibration) gets one panel per entry.
 */
function camerasOf(frame) {
  if (Array.isArray(frame.cameras)) {
    return frame.cameras.map((c, i) => ({ name: c.name ?? `camera ${i + 1}`, image: c.image, calibration: c.calibration }));
  }
  return [{ name: frame.camera_name ?? 'camera 1', image: frame.image, calibration: frame.calibration }];
}

/** The camera a person's 2D pose belongs to: the response's `camera`, else the only one. */
function cameraOf(pose, cameras) {
  if (pose.camera) return pose.camera;
  return cameras.length === 1 ? cameras[0].name : null;
}

function decodeBase64(b64) {
  const bin = atob(b64);
  const out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  return out;
}

/** LiDAR points as a Float32Array of xyz: a flat JSON array or {"b64": little-endian f32}. */
function decodePoints(points) {
  if (Array.isArray(points)) return Float32Array.from(points);
  if (points && typeof points.b64 === 'string') {
    const bytes = decodeBase64(points.b64);
    const view = new DataView(bytes.buffer);
    const out = new Float32Array(Math.floor(bytes.length / 4));
    for (let i = 0; i < out.length; i++) out[i] = view.getFloat32(i * 4, true);
    return out;
  }
  return new Float32Array(0);
}

/** A 3D box's local frame: point -> [along heading, across, up] relative to its centre. */
function toBox(b, x, y, z) {
  const dx = x - b.center_x;
  const dy = y - b.center_y;
  const c = Math.cos(b.heading);
  const s = Math.sin(b.heading);
  return [c * dx + s * dy, -s * dx + c * dy, z - b.center_z];
}

function fromBox(b, q) {
  const c = Math.cos(b.heading);
  const s = Math.sin(b.heading);
  return [b.center_x + c * q[0] - s * q[1], b.center_y + s * q[0] + c * q[1], b.center_z + q[2]];
}

function boxCorners(b) {
  const out = [];
  for (const sz of [-1, 1]) {
    for (const [sx, sy] of [[-1, -1], [1, -1], [1, 1], [-1, 1]]) {
      out.push(fromBox(b, [(sx * b.length) / 2, (sy * b.width) / 2, (sz * b.height) / 2]));
    }
  }
  return out;
}

/** Per-person 3D error against ground truth (docs/ARCHITECTURE.md, "Conventions"): MPJPE (m) and OKS. */
export function personMetrics(pred, truth, box) {
  if (!truth || !truth.xyz || !truth.visible) return null;
  const scale = Math.cbrt(box.length * box.width * box.height);
  const errors = new Array(pred.length).fill(null);
  let sumErr = 0;
  let sumOks = 0;
  let n = 0;
  for (let k = 0; k < pred.length; k++) {
    if (!truth.visible[k]) continue;
    const d = Math.hypot(pred[k][0] - truth.xyz[k][0], pred[k][1] - truth.xyz[k][1], pred[k][2] - truth.xyz[k][2]);
    const s = KP.oks_scales[k] * scale;
    errors[k] = d;
    sumErr += d;
    sumOks += Math.exp(-(d * d) / (2 * s * s));
    n++;
  }
  return n ? { mpjpe: sumErr / n, oks: sumOks / n, errors } : null;
}

/** Joins the answer's persons with the request's (by id) and gives each a colour. */
function buildPersons(frame, response, cameras) {
  const byId = new Map(frame.persons.map((p, i) => [p.id, { request: p, index: i }]));
  return response.persons.map((pose, i) => {
    const req = byId.get(pose.id) ?? { request: null, index: i };
    const truth = req.request?.ground_truth ?? null;
    const scores = pose.keypoints.map((k) => k.score).filter((s) => s !== null && s !== undefined);
    const pred = pose.keypoints.map((k) => k.xyz);
    return {
      pose,
      request: req.request,
      colour: personColour(req.index),
      camera: pose.mode === 'lidar' ? null : cameraOf(pose, cameras),
      panel: cameraOf(pose, cameras),
      score: scores.length ? scores.reduce((a, b) => a + b, 0) / scores.length : null,
      truth3d: truth?.keypoints_3d ?? null,
      truth2d: truth?.keypoints_2d ?? null,
      eval: req.request ? personMetrics(pred, truth?.keypoints_3d, req.request.box_3d) : null,
    };
  });
}

/** Points inside or within NEAR_M of a person's box (owner = that person when inside). */
function nearPoints(all, persons) {
  // Each box with a bounding sphere, so most points of a large scan are passed over quickly.
  const boxes = [];
  persons.forEach((p, pi) => {
    const b = p.request?.box_3d;
    if (b) boxes.push({ b, pi, r: Math.hypot(b.length, b.width, b.height) / 2 + NEAR_M * Math.sqrt(3) });
  });
  const keep = [];
  const owner = [];
  for (let i = 0; i + 2 < all.length; i += 3) {
    let own = -2;
    for (const { b, pi, r } of boxes) {
      const dx = all[i] - b.center_x;
      const dy = all[i + 1] - b.center_y;
      const dz = all[i + 2] - b.center_z;
      if (dx * dx + dy * dy + dz * dz > r * r) continue;
      const q = toBox(b, all[i], all[i + 1], all[i + 2]);
      const ax = Math.abs(q[0]) - b.length / 2;
      const ay = Math.abs(q[1]) - b.width / 2;
      const az = Math.abs(q[2]) - b.height / 2;
      if (ax <= 0 && ay <= 0 && az <= 0) {
        own = pi;
        break;
      }
      if (ax <= NEAR_M && ay <= NEAR_M && az <= NEAR_M) own = -1;
    }
    if (own >= -1) {
      keep.push(all[i], all[i + 1], all[i + 2]);
      owner.push(own);
    }
  }
  return { points: Float32Array.from(keep), owner: Int32Array.from(owner) };
}

// ---------------------------------------------------------------- formatting

const fmt = (v, digits = 2, unit = '') => (v === null || v === undefined || Number.isNaN(v) ? '–' : `${v.toFixed(digits)}${unit}`);

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === 'class') e.className = v;
    else if (k === 'text') e.textContent = v;
    else if (k.startsWith('data-') || k.startsWith('aria-') || k === 'role' || k === 'id' || k === 'scope') e.setAttribute(k, v);
    else e[k] = v;
  }
  for (const c of children) e.append(c);
  return e;
}

function pairs(dl, rows) {
  dl.replaceChildren();
  for (const [k, v] of rows) dl.append(el('dt', { text: k }), el('dd', { text: v }));
}

// ---------------------------------------------------------------- opening and sending

function setStatus(text) {
  $('status').textContent = text;
}

function showError(detail, where) {
  const box = $('error');
  box.replaceChildren(
    el('code', { text: detail.code ?? 'error' }),
    el('span', { class: 'message', text: detail.message ?? String(detail) }),
  );
  if (detail.field) box.append(el('span', { class: 'hint', text: ` (field ${detail.field})` }));
  if (where) box.append(el('div', { class: 'hint', text: where }));
  box.hidden = false;
}

function clearView() {
  Object.assign(state, { response: null, metrics: null, persons: [], skipped: [], cameras: [], selected: -1 });
  state.images.clear();
  state.points = null;
  state.pointOwner = null;
  $('cameras').replaceChildren();
  $('closeups').replaceChildren();
  $('closeups-wrap').hidden = true;
  $('persons').replaceChildren();
  $('persons').removeAttribute('aria-activedescendant');
  $('skipped').replaceChildren();
  $('timings').replaceChildren();
  $('metrics-section').hidden = true;
  renderDetail();
  drawScene();
}

/** Opens a file's text: one frame, or a JSON array of frames (the first is sent). */
async function openText(text, source) {
  state.source = source;
  let parsed;
  try {
    parsed = JSON.parse(text);
  } catch {
    // Let the API word what is wrong with it.
    state.frames = [];
    $('frame-choice').hidden = true;
    return send(text, null, source);
  }
  state.frames = Array.isArray(parsed) ? parsed : [parsed];
  const choice = $('frame-index');
  choice.replaceChildren(
    ...state.frames.map((f, i) => el('option', { value: String(i), text: `${i + 1}: ${f?.frame_id ?? 'frame'}` })),
  );
  $('frame-choice').hidden = state.frames.length < 2;
  if (!state.frames.length) {
    return showError({ code: 'empty', message: `${source} holds an empty array: no frame to send` });
  }
  return sendFrame(0);
}

function sendFrame(i) {
  const frame = state.frames[i];
  $('frame-index').value = String(i);
  const label = state.frames.length > 1 ? `${state.source} [${i + 1}/${state.frames.length}]` : state.source;
  return send(JSON.stringify(frame), frame, label);
}

function hasTruth(frame) {
  return Array.isArray(frame?.persons) && frame.persons.some((p) => p && p.ground_truth);
}

/** Sends the frame (to /v1/evaluate as `[frame]` when it has ground truth) and draws the answer. */
async function send(body, frame, label) {
  const evaluate = hasTruth(frame);
  const url = evaluate ? '/v1/evaluate' : '/v1/poses';
  document.body.dataset.state = 'loading';
  $('error').hidden = true;
  setStatus(`Sending ${label} (${(body.length / 1024).toFixed(0)} KB) to ${url} …`);
  const t0 = performance.now();
  let resp;
  let data;
  try {
    resp = await fetch(url, {
      method: 'POST',
      headers: { 'content-type': 'application/json' },
      body: evaluate ? `[${body}]` : body,
    });
    const text = await resp.text();
    try {
      data = JSON.parse(text);
    } catch {
      data = { error: { code: `http_${resp.status}`, message: text || resp.statusText } };
    }
  } catch (e) {
    clearView();
    showError({ code: 'network', message: `the server did not answer: ${e.message}` }, url);
    document.body.dataset.state = 'error';
    return setStatus(`${label}: no answer`);
  }
  state.roundTripMs = performance.now() - t0;
  let response = data;
  let error = resp.ok ? null : data.error ?? { code: `http_${resp.status}`, message: resp.statusText };
  if (!error && evaluate) {
    const item = data.predictions?.[0];
    error = item?.error ?? null;
    response = item?.response ?? null;
    state.metrics = error ? null : data.metrics?.all ?? null;
  } else {
    state.metrics = null;
  }
  if (error || !response) {
    clearView();
    showError(error ?? { code: 'unexpected', message: 'the answer holds no response' }, `${url} answered ${resp.status}`);
    document.body.dataset.state = 'error';
    return setStatus(`${label}: refused by the server`);
  }
  const metrics = state.metrics;
  clearView();
  state.metrics = metrics;
  try {
    await show(frame, response);
  } catch (e) {
    showError({ code: 'viewer', message: `cannot draw the answer: ${e.message}` });
    document.body.dataset.state = 'error';
    return undefined;
  }
  const n = response.persons.length;
  const skipped = response.skipped?.length ?? 0;
  setStatus(
    `${label}: ${n} person${n === 1 ? '' : 's'} answered${skipped ? `, ${skipped} skipped` : ''} by ` +
      `${response.model.name} ${response.model.version} via ${url}`,
  );
  document.body.dataset.state = 'ready';
  return undefined;
}

async function show(frame, response) {
  state.frame = frame;
  state.response = response;
  state.cameras = camerasOf(frame);
  state.persons = buildPersons(frame, response, state.cameras);
  state.skipped = response.skipped ?? [];
  for (const cam of state.cameras) {
    if (!cam.image) continue;
    try {
      state.images.set(cam.name, await createImageBitmap(new Blob([decodeBase64(cam.image)])));
    } catch {
      // The server decoded it (or would have said so); the panel says the browser could not.
    }
  }
  const near = nearPoints(decodePoints(frame.points), state.persons);
  state.points = near.points;
  state.pointOwner = near.owner;
  buildCameraPanels();
  buildCloseups();
  renderPersons();
  renderTimings();
  renderMetrics();
  resetView();
  select(state.persons.length ? 0 : -1);
}

// ---------------------------------------------------------------- camera panels

function buildCameraPanels() {
  const root = $('cameras');
  root.replaceChildren();
  $('cameras-h').textContent = state.cameras.length > 1 ? `Cameras (${state.cameras.length})` : 'Camera';
  for (const cam of state.cameras) {
    const { width, height } = cam.calibration;
    const onIt = state.persons.filter((p) => p.panel === cam.name).length;
    const img = state.images.has(cam.name) ? 'image' : cam.image ? 'image not decodable by the browser' : 'no image (LiDAR only)';
    const canvas = el('canvas', {
      role: 'img',
      'aria-label': `${cam.name}: ${img}, ${width}×${height} px, with the 2D poses of ${onIt} person${onIt === 1 ? '' : 's'}`,
      'data-camera': cam.name,
      'data-width': String(width),
      'data-height': String(height),
    });
    canvas.style.aspectRatio = `${width} / ${height}`;
    canvas.addEventListener('click', (ev) => pickOnCamera(ev, cam, canvas));
    root.append(el('figure', {}, el('figcaption', { text: `${cam.name} · ${width}×${height} · ${img}` }), canvas));
  }
  drawCameras();
}

function fitCanvas(canvas) {
  const r = canvas.getBoundingClientRect();
  const dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(r.width * dpr));
  const h = Math.max(1, Math.round(r.height * dpr));
  if (canvas.width !== w || canvas.height !== h) {
    canvas.width = w;
    canvas.height = h;
  }
  return { w: r.width, h: r.height, dpr };
}

function drawCameras() {
  for (const canvas of $('cameras').querySelectorAll('canvas')) {
    const cam = state.cameras.find((c) => c.name === canvas.dataset.camera);
    if (cam) drawCamera(canvas, cam);
  }
}

function drawCamera(canvas, cam) {
  const { w, dpr } = fitCanvas(canvas);
  const ctx = canvas.getContext('2d');
  const { width, height } = cam.calibration;
  const k = w / width; // image pixels -> CSS pixels
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.fillStyle = '#000';
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  const bitmap = state.images.get(cam.name);
  if (bitmap) ctx.drawImage(bitmap, 0, 0, width * k, height * k);
  else {
    ctx.fillStyle = '#8a9099';
    ctx.font = '14px system-ui, sans-serif';
    ctx.fillText('no camera image: 2D poses are the projections of the 3D ones', 12, 24);
  }
  const mine = state.persons.map((p, i) => [p, i]).filter(([p]) => p.panel === cam.name);
  // Highlighted person last; boxes and labels first, skeletons next, keypoints on top.
  mine.sort(([, a], [, b]) => (a === state.selected) - (b === state.selected));
  const uv = (kp) => [kp.uv[0] * k, kp.uv[1] * k];
  for (const [p, i] of mine) {
    const b = p.pose.box_2d;
    if (!b) continue;
    const sel = i === state.selected;
    const x = (b.center_x - b.width / 2) * k;
    const y = (b.center_y - b.height / 2) * k;
    if (sel) {
      ctx.strokeStyle = '#ffffff';
      ctx.lineWidth = 5;
      ctx.strokeRect(x, y, b.width * k, b.height * k);
    }
    ctx.strokeStyle = p.colour;
    ctx.lineWidth = sel ? 2.5 : 1.5;
    ctx.setLineDash(sel ? [] : [5, 3]);
    ctx.strokeRect(x, y, b.width * k, b.height * k);
    ctx.setLineDash([]);
    const label = `${p.pose.id} ${p.pose.mode}${p.score === null ? '' : ` ${p.score.toFixed(2)}`}`;
    ctx.font = `${sel ? 'bold ' : ''}11px system-ui, sans-serif`;
    const tw = ctx.measureText(label).width + 6;
    const lx = Math.max(0, Math.min(x, w - tw));
    const ly = y > 16 ? y - 15 : y + 1;
    ctx.fillStyle = 'rgba(0,0,0,0.7)';
    ctx.fillRect(lx, ly, tw, 14);
    ctx.fillStyle = p.colour;
    ctx.fillText(label, lx + 3, ly + 11);
  }
  if (state.selected >= 0 && $('show-truth').checked) {
    const p = state.persons[state.selected];
    if (p.panel === cam.name && p.truth2d) drawTruth2d(ctx, p.truth2d, (t) => [t[0] * k, t[1] * k]);
  }
  const map = (t) => [t[0] * k, t[1] * k];
  for (const [p, i] of mine) drawSkeleton2d(ctx, p, i === state.selected ? 3 : 2, map);
  for (const [p, i] of mine) drawKeypoints2d(ctx, p, i === state.selected ? 4.5 : 3.5, map);
}

/** A person's 2D skeleton; `map` takes image pixels to canvas pixels. */
function drawSkeleton2d(ctx, p, width, map) {
  const kps = p.pose.keypoints;
  ctx.strokeStyle = p.colour;
  ctx.lineWidth = width;
  ctx.lineCap = 'round';
  ctx.beginPath();
  for (const [a, b] of KP.skeleton) {
    if (!kps[a]?.uv || !kps[b]?.uv) continue;
    ctx.moveTo(...map(kps[a].uv));
    ctx.lineTo(...map(kps[b].uv));
  }
  ctx.stroke();
}

/** A person's keypoints: discs of the person's colour with a thin dark rim. */
function drawKeypoints2d(ctx, p, r, map) {
  for (const kp of p.pose.keypoints) {
    if (!kp.uv) continue;
    ctx.beginPath();
    ctx.arc(...map(kp.uv), r, 0, 2 * Math.PI);
    ctx.fillStyle = p.colour;
    ctx.fill();
    ctx.lineWidth = 1;
    ctx.strokeStyle = '#000000';
    ctx.stroke();
  }
}

/** Labelled 2D keypoints: white rings and a dashed skeleton. */
function drawTruth2d(ctx, t, map) {
  ctx.strokeStyle = '#ffffff';
  ctx.lineWidth = 1.5;
  ctx.setLineDash([4, 3]);
  ctx.beginPath();
  for (const [a, b] of KP.skeleton) {
    if (!t.visible[a] || !t.visible[b]) continue;
    ctx.moveTo(...map(t.uv[a]));
    ctx.lineTo(...map(t.uv[b]));
  }
  ctx.stroke();
  ctx.setLineDash([]);
  for (let i = 0; i < t.uv.length; i++) {
    if (!t.visible[i]) continue;
    ctx.beginPath();
    ctx.arc(...map(t.uv[i]), 5, 0, 2 * Math.PI);
    ctx.stroke();
  }
}

/** One enlarged view per person with a 2D box: the image around the box and the 2D pose. */
function buildCloseups() {
  const root = $('closeups');
  root.replaceChildren();
  state.persons.forEach((p, i) => {
    if (!p.pose.box_2d || !state.cameras.some((c) => c.name === p.panel)) return;
    const canvas = el('canvas', { role: 'img', 'aria-label': `close-up of ${p.pose.id} in ${p.panel}` });
    const caption = el('figcaption', { text: p.pose.id });
    caption.style.color = p.colour;
    const fig = el('figure', { class: 'closeup', 'data-person': String(i) }, canvas, caption);
    fig.addEventListener('click', () => select(i === state.selected ? -1 : i));
    root.append(fig);
  });
  $('closeups-wrap').hidden = !root.children.length;
}

function drawCloseups() {
  for (const fig of $('closeups').children) {
    const i = Number(fig.dataset.person);
    const p = state.persons[i];
    const cam = state.cameras.find((c) => c.name === p.panel);
    fig.classList.toggle('selected', i === state.selected);
    if (i === state.selected) reveal($('closeups'), fig);
    const canvas = fig.querySelector('canvas');
    const { w, h, dpr } = fitCanvas(canvas);
    const ctx = canvas.getContext('2d');
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = '#000';
    ctx.fillRect(0, 0, w, h);
    // The box grown by a quarter, widened or heightened to the canvas's shape.
    const b = p.pose.box_2d;
    let cw = b.width * 1.25;
    let ch = b.height * 1.25;
    if (cw / ch < w / h) cw = (ch * w) / h;
    else ch = (cw * h) / w;
    const sx = b.center_x - cw / 2;
    const sy = b.center_y - ch / 2;
    const k = w / cw;
    const bitmap = state.images.get(cam.name);
    if (bitmap) ctx.drawImage(bitmap, sx, sy, cw, ch, 0, 0, w, h);
    const map = (t) => [(t[0] - sx) * k, (t[1] - sy) * k];
    if (i === state.selected && p.truth2d && $('show-truth').checked) drawTruth2d(ctx, p.truth2d, map);
    drawSkeleton2d(ctx, p, 2, map);
    drawKeypoints2d(ctx, p, 3, map);
  }
}

function pickOnCamera(ev, cam, canvas) {
  const r = canvas.getBoundingClientRect();
  const k = r.width / cam.calibration.width;
  const u = (ev.clientX - r.left) / k;
  const v = (ev.clientY - r.top) / k;
  let best = -1;
  let bestArea = Infinity;
  state.persons.forEach((p, i) => {
    const b = p.pose.box_2d;
    if (!b || p.panel !== cam.name) return;
    const inside = Math.abs(u - b.center_x) <= b.width / 2 && Math.abs(v - b.center_y) <= b.height / 2;
    if (inside && b.width * b.height < bestArea) {
      best = i;
      bestArea = b.width * b.height;
    }
  });
  select(best === state.selected ? -1 : best);
}

// ---------------------------------------------------------------- persons list and details

function renderPersons() {
  const list = $('persons');
  list.replaceChildren();
  state.persons.forEach((p, i) => {
    const pose = p.pose;
    const facts = [
      `${pose.num_points} points`,
      p.camera ? `uses ${p.camera}` : 'LiDAR only',
    ];
    if (p.eval) facts.push(`MPJPE ${fmt(p.eval.mpjpe, 3, ' m')}`, `OKS ${fmt(p.eval.oks, 2)}`);
    const li = el(
      'li',
      {
        id: `person-${i}`,
        role: 'option',
        'aria-selected': 'false',
        'data-id': pose.id,
        'data-colour': p.colour,
        'data-mode': pose.mode,
        title: pose.mode_reason,
      },
      el('span', { class: 'swatch', 'aria-hidden': 'true' }),
      el('span', { class: 'name', text: pose.id }),
      el('span', { class: 'mode', text: `${pose.mode}${p.score === null ? '' : ` · score ${p.score.toFixed(2)}`}` }),
      el('span', { class: 'facts', text: facts.join(' · ') }),
    );
    if (p.eval) {
      li.dataset.mpjpe = String(p.eval.mpjpe);
      li.dataset.oks = String(p.eval.oks);
    }
    li.querySelector('.swatch').style.background = p.colour;
    li.addEventListener('click', () => select(i === state.selected ? -1 : i));
    list.append(li);
  });
  const skipped = $('skipped');
  skipped.replaceChildren();
  if (state.skipped.length) {
    skipped.append(
      el('h3', { class: 'hint', text: `Skipped (${state.skipped.length}): no pose` }),
      el('ul', { class: 'skipped' }, ...state.skipped.map((s) => el('li', { text: `${s.id}: ${s.error.message} (${s.error.code})` }))),
    );
  }
}

function renderDetail() {
  const root = $('detail');
  const p = state.persons[state.selected];
  if (!p) {
    root.replaceChildren(el('p', { class: 'hint', text: state.persons.length ? 'None: every person is shown alike.' : 'No frame yet.' }));
    return;
  }
  const pose = p.pose;
  const dl = el('dl', { class: 'pairs' });
  const b = pose.box_2d;
  pairs(dl, [
    ['id', pose.id],
    ['mode', pose.mode],
    ['why', pose.mode_reason],
    ['camera', p.camera ?? 'none (LiDAR only)'],
    ['score', fmt(p.score, 2)],
    ['points in box', String(pose.num_points)],
    ['2D box', b ? `${b.center_x.toFixed(0)}, ${b.center_y.toFixed(0)} · ${b.width.toFixed(0)}×${b.height.toFixed(0)} px` : 'outside the image'],
    ...(p.eval ? [['MPJPE', fmt(p.eval.mpjpe, 3, ' m')], ['OKS', fmt(p.eval.oks, 3)]] : []),
  ]);
  const cols = ['keypoint', 'x, y, z (m)', 'u, v (px)', 'score', ...(p.eval ? ['error (m)'] : [])];
  const head = el('tr', {}, ...cols.map((h) => el('th', { scope: 'col', text: h })));
  const rows = pose.keypoints.map((kp, k) =>
    el(
      'tr',
      {},
      el('th', { scope: 'row', text: kp.name.replace('_', ' ') }),
      el('td', { text: kp.xyz.map((v) => v.toFixed(2)).join(', ') }),
      el('td', { text: kp.uv ? kp.uv.map((v) => v.toFixed(0)).join(', ') : '–' }),
      el('td', { text: fmt(kp.score, 2) }),
      ...(p.eval ? [el('td', { text: fmt(p.eval.errors[k], 3) })] : []),
    ),
  );
  const table = el('table', { class: 'keypoints' }, el('caption', { class: 'hint', text: `Keypoints of ${pose.id} (vehicle frame, m; image, px)` }), el('thead', {}, head), el('tbody', {}, ...rows));
  root.replaceChildren(dl, table);
}

function renderTimings() {
  const t = state.response.timings;
  pairs($('timings'), [
    ['decode', fmt(t.decode_ms, 1, ' ms')],
    ['pre-process', fmt(t.preprocess_ms, 1, ' ms')],
    ['queue', fmt(t.queue_ms, 1, ' ms')],
    ['inference', fmt(t.inference_ms, 1, ' ms')],
    ['total (server)', fmt(t.total_ms, 1, ' ms')],
    ['round trip (browser)', fmt(state.roundTripMs, 1, ' ms')],
  ]);
}

function renderMetrics() {
  const m = state.metrics;
  $('metrics-section').hidden = !m;
  if (!m) return;
  pairs($('metrics'), [
    ['persons scored', `${m.count_3d} (3D), ${m.count_2d} (2D)`],
    ['mean OKS 3D', fmt(m.mean_oks_3d, 3)],
    ['OKS/ACC 3D', fmt(m.oks_acc_3d, 3)],
    ['MPJPE 3D', fmt(m.mpjpe_3d_m, 3, ' m')],
    ['PCK 3D @ 10 cm', fmt(m.pck_3d_10cm, 3)],
    ['PEM 3D', fmt(m.pem_3d_m, 3, ' m')],
    ['mean OKS 2D', fmt(m.mean_oks_2d, 3)],
    ['MPJPE 2D', fmt(m.mpjpe_2d_px, 1, ' px')],
  ]);
}

/** Scrolls `container` (not the page) so that `child` is in view. */
function reveal(container, child) {
  const c = container.getBoundingClientRect();
  const r = child.getBoundingClientRect();
  if (r.top < c.top) container.scrollTop -= c.top - r.top;
  else if (r.bottom > c.bottom) container.scrollTop += r.bottom - c.bottom;
  if (r.left < c.left) container.scrollLeft -= c.left - r.left;
  else if (r.right > c.right) container.scrollLeft += r.right - c.right;
}

/** Selects person `i` (-1: none): list, details, camera and 3D view follow. */
function select(i) {
  state.selected = i >= 0 && i < state.persons.length ? i : -1;
  const list = $('persons');
  for (const li of list.children) {
    const on = li.id === `person-${state.selected}`;
    li.setAttribute('aria-selected', String(on));
    li.classList.toggle('active', on);
  }
  if (state.selected >= 0) {
    list.setAttribute('aria-activedescendant', `person-${state.selected}`);
    reveal(list, $(`person-${state.selected}`));
  } else {
    list.removeAttribute('aria-activedescendant');
  }
  renderDetail();
  centreView();
  drawCameras();
  drawCloseups();
  drawScene();
}

function step(delta) {
  const n = state.persons.length;
  if (!n) return;
  select(state.selected < 0 ? (delta > 0 ? 0 : n - 1) : (state.selected + delta + n) % n);
}

function onListKey(ev) {
  const keys = { ArrowDown: 1, ArrowUp: -1, j: 1, k: -1 };
  if (ev.key in keys) step(keys[ev.key]);
  else if (ev.key === 'Home') select(0);
  else if (ev.key === 'End') select(state.persons.length - 1);
  else if (ev.key === 'Escape') select(-1);
  else return;
  ev.preventDefault();
}

// ---------------------------------------------------------------- 3D view

function resetView() {
  state.view.yaw = Math.PI;
  state.view.pitch = 0.45;
  centreView(true);
}

/** Centres the view on the selected person, or on every box; `fit` also sets the distance. */
function centreView(fit = false) {
  const v = state.view;
  const boxes = (state.selected >= 0 ? [state.persons[state.selected]] : state.persons)
    .map((p) => p.request?.box_3d)
    .filter(Boolean);
  if (!boxes.length) return;
  const lo = [Infinity, Infinity, Infinity];
  const hi = [-Infinity, -Infinity, -Infinity];
  for (const b of boxes) {
    for (const c of boxCorners(b)) {
      for (let a = 0; a < 3; a++) {
        lo[a] = Math.min(lo[a], c[a]);
        hi[a] = Math.max(hi[a], c[a]);
      }
    }
  }
  v.target = [0, 1, 2].map((a) => (lo[a] + hi[a]) / 2);
  const extent = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
  if (fit || state.selected >= 0) v.dist = Math.max(3.5, extent * 1.6);
}

/** A perspective camera orbiting the target: vehicle frame (z up) -> canvas CSS pixels. */
function projector(w, h) {
  const v = state.view;
  const cp = Math.cos(v.pitch);
  const eye = [
    v.target[0] + v.dist * cp * Math.cos(v.yaw),
    v.target[1] + v.dist * cp * Math.sin(v.yaw),
    v.target[2] + v.dist * Math.sin(v.pitch),
  ];
  const f = v.target.map((t, a) => (t - eye[a]) / v.dist);
  const rl = Math.hypot(f[0], f[1]) || 1;
  const r = [f[1] / rl, -f[0] / rl, 0]; // f × z
  const u = [r[1] * f[2] - r[2] * f[1], r[2] * f[0] - r[0] * f[2], r[0] * f[1] - r[1] * f[0]];
  const focal = (0.5 * h) / Math.tan((50 * Math.PI) / 360);
  const depth = (p) => (p[0] - eye[0]) * f[0] + (p[1] - eye[1]) * f[1] + (p[2] - eye[2]) * f[2];
  const P = (p) => {
    const d = [p[0] - eye[0], p[1] - eye[1], p[2] - eye[2]];
    const z = d[0] * f[0] + d[1] * f[1] + d[2] * f[2];
    if (z < NEAR_PLANE) return null;
    const x = d[0] * r[0] + d[1] * r[1] + d[2] * r[2];
    const y = d[0] * u[0] + d[1] * u[1] + d[2] * u[2];
    return [w / 2 + (focal * x) / z, h / 2 - (focal * y) / z, z];
  };
  P.depth = depth;
  return P;
}

const NEAR_PLANE = 0.1;

/** A 3D segment, cut at the near plane. */
function line3(ctx, P, a, b) {
  const za = P.depth(a);
  const zb = P.depth(b);
  if (za < NEAR_PLANE && zb < NEAR_PLANE) return;
  if (za < NEAR_PLANE || zb < NEAR_PLANE) {
    const t = (NEAR_PLANE + 1e-6 - za) / (zb - za);
    const m = [0, 1, 2].map((i) => a[i] + t * (b[i] - a[i]));
    if (za < NEAR_PLANE) a = m;
    else b = m;
  }
  const pa = P(a);
  const pb = P(b);
  if (!pa || !pb) return;
  ctx.moveTo(pa[0], pa[1]);
  ctx.lineTo(pb[0], pb[1]);
}

function drawSkeleton3d(ctx, P, xyz, visible, colour, width, dash) {
  ctx.strokeStyle = colour;
  ctx.lineWidth = width;
  ctx.setLineDash(dash);
  ctx.beginPath();
  for (const [a, b] of KP.skeleton) {
    if (visible && (!visible[a] || !visible[b])) continue;
    line3(ctx, P, xyz[a], xyz[b]);
  }
  ctx.stroke();
  ctx.setLineDash([]);
  ctx.fillStyle = colour;
  xyz.forEach((p, k) => {
    if (visible && !visible[k]) return;
    const s = P(p);
    if (!s) return;
    ctx.beginPath();
    ctx.arc(s[0], s[1], dash.length ? 2.5 : width + 0.5, 0, 2 * Math.PI);
    if (dash.length) ctx.stroke();
    else ctx.fill();
  });
}

function drawScene() {
  const canvas = $('scene');
  const { w, h, dpr } = fitCanvas(canvas);
  const ctx = canvas.getContext('2d');
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.fillStyle = '#0c0d10';
  ctx.fillRect(0, 0, w, h);
  if (!state.persons.length) {
    canvas.setAttribute('aria-label', '3D view: no frame yet');
    return;
  }
  const P = projector(w, h);
  const showTruth = $('show-truth').checked;
  // Ground grid under the boxes (1 m; 5 m over wide scenes).
  const lo = [Infinity, Infinity];
  const hi = [-Infinity, -Infinity];
  let gz = Infinity;
  for (const p of state.persons) {
    const b = p.request?.box_3d;
    if (!b) continue;
    lo[0] = Math.min(lo[0], b.center_x);
    lo[1] = Math.min(lo[1], b.center_y);
    hi[0] = Math.max(hi[0], b.center_x);
    hi[1] = Math.max(hi[1], b.center_y);
    gz = Math.min(gz, b.center_z - b.height / 2);
  }
  if (Number.isFinite(gz)) {
    const cell = Math.max(hi[0] - lo[0], hi[1] - lo[1]) > 60 ? 5 : 1;
    const g0 = lo.map((v) => Math.floor(v / cell - 3) * cell);
    const g1 = hi.map((v) => Math.ceil(v / cell + 3) * cell);
    ctx.strokeStyle = '#2a2f37';
    ctx.lineWidth = 1;
    ctx.beginPath();
    for (let x = g0[0]; x <= g1[0] + 1e-9; x += cell) line3(ctx, P, [x, g0[1], gz], [x, g1[1], gz]);
    for (let y = g0[1]; y <= g1[1] + 1e-9; y += cell) line3(ctx, P, [g0[0], y, gz], [g1[0], y, gz]);
    ctx.stroke();
  }
  // Points: in a box in its person's colour, near one in grey.
  const pts = state.points;
  const owner = state.pointOwner;
  const showNear = $('show-near').checked;
  if (pts) {
    for (let i = 0; i < owner.length; i++) {
      const o = owner[i];
      if (o < 0 && !showNear) continue;
      const s = P([pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]]);
      if (!s) continue;
      const size = Math.max(1.2, Math.min(3, 30 / s[2]));
      ctx.fillStyle = o >= 0 ? state.persons[o].colour : '#6b7280';
      ctx.globalAlpha = o >= 0 && state.selected >= 0 && o !== state.selected ? 0.35 : 0.8;
      ctx.fillRect(s[0] - size / 2, s[1] - size / 2, size, size);
    }
    ctx.globalAlpha = 1;
  }
  // Boxes, then skeletons (the selected person's last and thicker).
  const order = state.persons.map((p, i) => i).sort((a, b) => (a === state.selected) - (b === state.selected));
  for (const i of order) {
    const p = state.persons[i];
    const b = p.request?.box_3d;
    if (!b) continue;
    const c = boxCorners(b);
    ctx.strokeStyle = p.colour;
    ctx.globalAlpha = i === state.selected ? 0.9 : 0.4;
    ctx.lineWidth = 1;
    ctx.beginPath();
    for (let e = 0; e < 4; e++) {
      line3(ctx, P, c[e], c[(e + 1) % 4]);
      line3(ctx, P, c[4 + e], c[4 + ((e + 1) % 4)]);
      line3(ctx, P, c[e], c[4 + e]);
    }
    ctx.stroke();
    ctx.globalAlpha = 1;
    const top = P(fromBox(b, [0, 0, b.height / 2 + 0.15]));
    if (top) {
      ctx.fillStyle = p.colour;
      ctx.font = `${i === state.selected ? 'bold ' : ''}11px system-ui, sans-serif`;
      ctx.fillText(p.pose.id, top[0] - 8, top[1]);
    }
  }
  for (const i of order) {
    const p = state.persons[i];
    const sel = i === state.selected;
    if (showTruth && p.truth3d) drawSkeleton3d(ctx, P, p.truth3d.xyz, p.truth3d.visible, '#f5f5f5', sel ? 2 : 1.2, [4, 3]);
    drawSkeleton3d(ctx, P, p.pose.keypoints.map((k) => k.xyz), null, p.colour, sel ? 3 : 2, []);
  }
  const who = state.selected >= 0 ? `centred on ${state.persons[state.selected].pose.id}` : 'all persons';
  canvas.setAttribute(
    'aria-label',
    `3D view of ${owner ? owner.length : 0} LiDAR points in or near the boxes and the 3D poses of ` +
      `${state.persons.length} persons${showTruth && state.persons.some((p) => p.truth3d) ? ' with ground truth (dashed)' : ''}, ${who}`,
  );
}

function sceneInput() {
  const canvas = $('scene');
  let drag = null;
  canvas.addEventListener('pointerdown', (ev) => {
    drag = { x: ev.clientX, y: ev.clientY };
    canvas.setPointerCapture(ev.pointerId);
  });
  canvas.addEventListener('pointermove', (ev) => {
    if (!drag) return;
    turn((ev.clientX - drag.x) * -0.01, (ev.clientY - drag.y) * 0.01);
    drag = { x: ev.clientX, y: ev.clientY };
  });
  const end = () => {
    drag = null;
  };
  canvas.addEventListener('pointerup', end);
  canvas.addEventListener('pointercancel', end);
  canvas.addEventListener(
    'wheel',
    (ev) => {
      ev.preventDefault();
      zoom(Math.exp(ev.deltaY * 0.001));
    },
    { passive: false },
  );
  canvas.addEventListener('keydown', (ev) => {
    const a = 0.08;
    const keys = {
      ArrowLeft: () => turn(a, 0),
      ArrowRight: () => turn(-a, 0),
      ArrowUp: () => turn(0, a),
      ArrowDown: () => turn(0, -a),
      '+': () => zoom(1 / 1.15),
      '=': () => zoom(1 / 1.15),
      '-': () => zoom(1.15),
      0: () => {
        resetView();
        drawScene();
      },
    };
    if (!(ev.key in keys)) return;
    keys[ev.key]();
    ev.preventDefault();
  });
}

function turn(dyaw, dpitch) {
  const v = state.view;
  v.yaw += dyaw;
  v.pitch = Math.max(-0.2, Math.min(1.5, v.pitch + dpitch));
  drawScene();
}

function zoom(factor) {
  state.view.dist = Math.max(1, Math.min(300, state.view.dist * factor));
  drawScene();
}

// ---------------------------------------------------------------- start

async function loadExamples() {
  try {
    const names = await (await fetch('/viewer/examples')).json();
    $('example').append(...names.map((n) => el('option', { value: n, text: n })));
  } catch {
    // No examples: the picker stays empty.
  }
}

async function openExample(name) {
  if (!name) return;
  const resp = await fetch(`/viewer/examples/${encodeURIComponent(name)}`);
  const text = await resp.text();
  if (!resp.ok) {
    showError(JSON.parse(text).error ?? { code: `http_${resp.status}`, message: text });
    return;
  }
  await openText(text, name);
}

async function openFile(file) {
  if (!file) return;
  await openText(await file.text(), file.name);
}

function dragAndDrop() {
  let depth = 0;
  document.addEventListener('dragenter', (ev) => {
    ev.preventDefault();
    depth++;
    document.body.classList.add('dragging');
  });
  document.addEventListener('dragover', (ev) => ev.preventDefault());
  document.addEventListener('dragleave', () => {
    depth = Math.max(0, depth - 1);
    if (!depth) document.body.classList.remove('dragging');
  });
  document.addEventListener('drop', (ev) => {
    ev.preventDefault();
    depth = 0;
    document.body.classList.remove('dragging');
    openFile(ev.dataTransfer?.files?.[0]);
  });
}

async function main() {
  KP = await (await fetch('/viewer/keypoints.json')).json();
  $('file').addEventListener('change', (ev) => openFile(ev.target.files[0]));
  $('example').addEventListener('change', (ev) => openExample(ev.target.value));
  $('frame-index').addEventListener('change', (ev) => sendFrame(Number(ev.target.value)));
  $('open').addEventListener('submit', (ev) => ev.preventDefault());
  $('persons').addEventListener('keydown', onListKey);
  $('view-reset').addEventListener('click', () => {
    resetView();
    drawScene();
  });
  for (const id of ['show-truth', 'show-near']) {
    $(id).addEventListener('change', () => {
      drawCameras();
      drawCloseups();
      drawScene();
    });
  }
  document.addEventListener('keydown', (ev) => {
    const t = ev.target;
    if (ev.defaultPrevented || ev.ctrlKey || ev.metaKey || ev.altKey) return;
    if (t instanceof HTMLInputElement || t instanceof HTMLSelectElement || t === $('persons')) return;
    if (ev.key === 'j' || ev.key === 'k') {
      step(ev.key === 'j' ? 1 : -1);
      ev.preventDefault();
    } else if (ev.key === 'Escape') select(-1);
  });
  sceneInput();
  dragAndDrop();
  new ResizeObserver(() => {
    drawCameras();
    drawCloseups();
    drawScene();
  }).observe(document.querySelector('main'));
  await loadExamples();
  document.body.dataset.state = 'idle';
}

main().catch((e) => {
  showError({ code: 'viewer', message: `cannot start: ${e.message}` });
});
