// The isosr viewer page: controls, camera, frames of one or two view sessions, live numbers.
import { PROTOCOL_VERSION, ViewSession } from "./session.js";
import { drawLegend } from "./legend.js";
import { FrameDecoder, IMAGE_ENCODINGS, VIDEO_PROBES, decodableEncodings } from "./video.js";

const $ = (id) => document.getElementById(id);
const DEFAULT_CAMERA = { yaw: 30, pitch: 20, distance: 1.8, target: [0, 0, 0], fov_y: 40 };
const CHANNELS = ["shaded", "mask", "normal", "depth", "ao", "flow"];
const AXES = ["x", "y", "z"]; // the world's, as the clip plane, the crop box and the slices name them
// Keys 1..9 pick the modes in the menu's order (the server's, GET /v1/modes).
const TOKEN_KEY = "isosr.token";
const SPARK_FRAMES = 120;
const MAX_PINNED = 3; // surfaces pinned besides the slider's (settings.surfaces: at most 4)
const VIDEO_ENCODINGS = Object.keys(VIDEO_PROBES);
// What "auto" asks for: the best video both sides have, else jpeg.
const AUTO_ENCODINGS = [...VIDEO_ENCODINGS, "jpeg"];

const view = $("view");
const ctx = view.getContext("2d");
const state = {
  token: sessionStorage.getItem(TOKEN_KEY) || "",
  factor: 4,
  modes: {}, // name -> the server's ModeInfo (label, options with bounds, shaded, low_res, focus): GET /v1/modes
  limits: null,
  decodable: new Set(IMAGE_ENCODINGS), // what this browser shows (decodableEncodings)
  encoders: null, // ready.encoders: what the server makes (null: no ready yet)
  volume: null,
  info: null, // ready.volume: name, shape, value_range, iso, histogram
  iso: null, // data units; null: the volume's suggested iso
  surfaces: [], // surfaces pinned besides the slider's iso: [{iso (data units), color [r, g, b]}]
  step: 0, // a series' time step shown (settings.t)
  playing: null, // the playback timer while a series plays
  camera: structuredClone(DEFAULT_CAMERA),
  width: 320,
  height: 240,
  split: 0.5,
  pointer: null,
  clipFlip: false, // the clip plane keeps the side above its offset
  sessions: [], // [{session, mode, image, frameId, stats, method}]
  pending: {},
  generation: 0, // of openSessions calls
  pendingPick: null, // the pick asked last: {id, x, y}
  picks: [], // the last two hits: [{x, y, picked}] (screen point and the server's answer)
  pickId: 0,
  slicesAt: null, // the voxel the slice strip goes through
};

// ---- server calls ------------------------------------------------------------------------------

function authHeaders() {
  return state.token ? { Authorization: `Bearer ${state.token}` } : {};
}

/** GET a JSON endpoint; throws an Error whose .status is the HTTP status (0: no answer). */
async function getJson(path) {
  let response;
  try {
    response = await fetch(path, { headers: authHeaders(), cache: "no-store" });
  } catch (e) {
    throw Object.assign(new Error(`no answer from the server (${e.message})`), { status: 0 });
  }
  const body = await response.json().catch(() => ({}));
  if (!response.ok) {
    const reason = body.error || response.statusText;
    throw Object.assign(new Error(`${response.status}: ${reason}`), { status: response.status });
  }
  return body;
}

function wsUrl() {
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  return `${scheme}//${location.host}/v1/view`;
}

// ---- status ------------------------------------------------------------------------------------

function setBanner(text, kind = "error") {
  const banner = $("banner");
  banner.hidden = !text;
  banner.textContent = text || "";
  banner.dataset.kind = kind;
}

function setNotice(text) {
  $("notice").hidden = !text;
  $("notice").textContent = text || "";
}

function setConnState(name, text) {
  const el = $("conn-state");
  el.dataset.state = name;
  el.textContent = text || name;
  view.classList.toggle("stale", name === "lost" || name === "error");
}

// ---- sessions ----------------------------------------------------------------------------------

function modes() {
  const a = $("mode").value;
  return $("split").checked ? [a, $("mode-b").value] : [a];
}

/** A mode's option (the server's OptionInfo) by name, or undefined where the mode does not read it. */
function option(mode, name) {
  return (state.modes[mode]?.options || []).find((o) => o.name === name);
}

/** Whether any shown mode has the trait (a ModeInfo flag) or reads the option. */
const anyShown = (test) => modes().some((m) => state.modes[m] && test(state.modes[m]));
const shownFocus = () => anyShown((m) => m.focus);

/** AO rays per hit: the control's value within the mode's bounds and the server's limit (shown corrected
 * for the left mode). */
function aoRays(mode) {
  const bounds = option(mode, "ao_rays");
  if (!bounds) return 0;
  const input = $("ao-rays");
  const high = Math.min(bounds.high, state.limits ? state.limits.max_ao_rays : Infinity);
  const rays = Math.min(high, Math.max(bounds.low, Math.round(Number(input.value)) || 0));
  if (mode === modes()[0]) input.value = rays;
  return rays;
}

/** The mode menus from the server's modes (those that make shaded images; the left one starts at
 * the server's first, the right one at its second) and the interpolation menu from its choices. */
function fillModeMenus(infos) {
  state.modes = Object.fromEntries(infos.map((m) => [m.name, m]));
  const shaded = infos.filter((m) => m.shaded);
  for (const [index, id] of ["mode", "mode-b"].entries()) {
    const menu = $(id);
    const picked = menu.value;
    menu.replaceChildren(...shaded.map((m) => new Option(m.label, m.name)));
    menu.value = state.modes[picked] ? picked : shaded[Math.min(index, shaded.length - 1)].name;
  }
  const interpolation = infos.flatMap((m) => m.options).find((o) => o.name === "interpolation");
  if (interpolation) {
    $("interpolation").replaceChildren(...interpolation.choices.map((c) => new Option(c, c)));
    $("interpolation").value = interpolation.default;
  }
}

/** The encoding to ask for: the one picked, or (auto) the best this browser shows among those the
 * server makes (any, until a ready says). */
function encoding() {
  const picked = $("encoding").value;
  if (picked !== "auto") return picked;
  return AUTO_ENCODINGS.find((e) => state.decodable.has(e) && (!state.encoders || state.encoders.includes(e)));
}

/** Why auto sends jpeg ("" when it sends video, or an encoding was picked). */
function autoNotice() {
  if ($("encoding").value !== "auto" || encoding() !== "jpeg") return "";
  const shown = VIDEO_ENCODINGS.filter((e) => state.decodable.has(e));
  if (!shown.length) {
    const why = window.isSecureContext ? "no WebCodecs decoder for h264, vp9 or av1" : "WebCodecs needs https or loopback";
    return `this browser decodes no video here (${why}); sending jpeg`;
  }
  return `the server makes none of the video codecs this browser decodes (${shown.join(", ")}); sending jpeg`;
}

/** Encodings either side lacks are greyed out in the menu, saying which side. */
function markEncodings() {
  for (const option of $("encoding").options) {
    const browser = VIDEO_ENCODINGS.includes(option.value) && !state.decodable.has(option.value);
    const server = state.encoders && option.value !== "auto" && !state.encoders.includes(option.value);
    option.disabled = browser || server;
    option.title = browser ? "this browser cannot decode it" : server ? "the server cannot make it" : "";
  }
}

/** The video bitrate cap in kbit/s: the control's value within the server's bound (shown corrected). */
function bitrate() {
  const input = $("bitrate");
  const most = state.limits ? state.limits.max_bitrate_kbps : Infinity;
  const kbps = Math.min(most, Math.max(0, Math.round(Number(input.value)) || 0));
  input.value = kbps;
  return kbps;
}

function settings(mode) {
  return {
    mode,
    width: state.width,
    height: state.height,
    ao_rays: aoRays(mode),
    interpolation: $("interpolation").value,
    channel: $("channel").value,
    // A refined frame is full-res: when split, both halves would be the same.
    refine: $("refine").checked && !$("split").checked,
    encoding: encoding(),
    quality: 90,
    bitrate_kbps: bitrate(),
    clip: clipSettings(),
    // Several surfaces show their own colours: the server takes no coloring beside them.
    coloring: state.surfaces.length ? null : coloringSettings(),
    t: state.step,
    surfaces: surfaceSettings(),
  };
}

/** The clip of the controls (settings.clip): the plane across the chosen world axis at the handle's
 * offset, keeping the side below it (above once flipped), none while off; and the crop box. */
function clipSettings() {
  const axis = AXES.indexOf($("clip-axis").value);
  $("clip-value").textContent = axis < 0 ? "" : `${state.clipFlip ? ">=" : "<="} ${$("clip-offset").value}`;
  const box = cropBox();
  const cap = $("cap").value;
  if (axis < 0) return { planes: [], box, cap };
  const point = [0, 0, 0];
  const normal = [0, 0, 0];
  point[axis] = Number($("clip-offset").value);
  normal[axis] = state.clipFlip ? 1 : -1;
  return { planes: [{ point, normal }], box, cap };
}

/** The crop box of the six handles ([lo, hi] in world units): per axis the span between its two
 * handles, in either order; null while every span is whole. */
function cropBox() {
  const lo = [];
  const hi = [];
  for (const axis of AXES) {
    const a = Number($(`crop-${axis}-lo`).value);
    const b = Number($(`crop-${axis}-hi`).value);
    lo.push(Math.min(a, b));
    hi.push(Math.max(a, b));
  }
  const whole = lo.every((v) => v <= -0.5) && hi.every((v) => v >= 0.5);
  $("crop-value").textContent = whole ? "" : AXES.map((a, i) => `${a} ${lo[i]}…${hi[i]}`).join(", ");
  return whole ? null : [lo, hi];
}

/** What colours the surface (settings.coloring): null, the gradient, or the named volume of the grid. */
function coloringSettings() {
  const by = $("color-by").value;
  $("color-field").hidden = by !== "field";
  const name = by === "field" ? $("color-field").value.trim() : by;
  if (by === "none" || !name) return null;
  return { by: name, colormap: $("colormap").value, range: null };
}

/** settings.surfaces: none while nothing is pinned, else the slider's iso in the material's colour and the
 * pinned ones (an iso equal to the slider's left out: the server refuses two equal isos). */
function surfaceSettings() {
  if (!state.surfaces.length || state.iso === null) return [];
  const pinned = state.surfaces.filter((s) => s.iso !== state.iso);
  return [{ iso: state.iso }, ...pinned]; // without a colour: the material's
}

/** Pin the slider's iso as a surface in the chosen colour and opacity (up to 3 besides the slider's). */
function addSurface() {
  if (state.iso === null || state.surfaces.length >= MAX_PINNED) return;
  const hex = $("surface-color").value;
  const color = [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255);
  const given = Number($("surface-opacity").value);
  const opacity = Number.isFinite(given) ? Math.min(1, Math.max(0, given)) : 1;
  state.surfaces = [...state.surfaces.filter((s) => s.iso !== state.iso), { iso: state.iso, color, opacity }];
  showSurfaces();
  sendSettings();
}

/** The pinned surfaces as swatches with their isos. */
function showSurfaces() {
  $("surface-list").replaceChildren(...state.surfaces.map((s) => {
    const swatch = document.createElement("span");
    swatch.textContent = `\u25A0 ${formatNumber(s.iso)}${s.opacity < 1 ? ` (${Math.round(100 * s.opacity)}%)` : ""} `;
    swatch.style.color = `rgb(${s.color.map((c) => Math.round(255 * c)).join(",")})`;
    return swatch;
  }));
  $("surface-add").disabled = state.surfaces.length >= MAX_PINNED;
}

/** Move the clip plane's handle by ``delta`` world units (within its range). */
function moveClip(delta) {
  const handle = $("clip-offset");
  handle.value = Math.min(Number(handle.max), Math.max(Number(handle.min), Number(handle.value) + delta)).toFixed(2);
  sendSettings();
}

/** The clip plane across the next axis (off, x, y, z). */
function cycleClip() {
  const axis = $("clip-axis");
  axis.selectedIndex = (axis.selectedIndex + 1) % axis.options.length;
  sendSettings();
}

function cameraMessage() {
  const c = state.camera;
  return { type: "camera", yaw: c.yaw, pitch: c.pitch, distance: c.distance, target: c.target, fov_y: c.fov_y };
}

function focusMessage() {
  const p = state.pointer || { x: state.width / 2, y: state.height / 2 };
  return { type: "focus", shape: "circle", center: [p.x, p.y], radius: Number($("lens-radius").value) };
}

function newStats() {
  return { arrivals: [], intervals: [], latency: null, times: null, bytes: 0 };
}

/** Close all sessions and open one per shown mode, for the current volume and state. */
async function openSessions() {
  for (const s of state.sessions) {
    s.session.close();
    s.decoder.reset();
  }
  state.sessions = [];
  const generation = ++state.generation; // a later call supersedes this one
  if (!state.volume) return;
  try {
    state.factor = (await getJson("/v2/models/isosr")).parameters.upscale_factor;
    if (!Object.keys(state.modes).length) {
      fillModeMenus((await getJson("/v1/modes")).modes);
      aoDefault();
    }
  } catch (e) {
    return generation === state.generation && serverUnreachable(e);
  }
  if (generation !== state.generation) return;
  resize(false);
  for (const [index, mode] of modes().entries()) {
    const slot = { mode, image: null, frameId: 0, shownId: 0, stats: newStats(), refined: false, device: null };
    slot.session = new ViewSession(wsUrl(), state.token, () => openMessage(slot), {
      onReady: (ready) => onReady(slot, index, ready),
      onFrame: (frame, latency) => onFrame(slot, frame, latency),
      onNotice: setNotice,
      onPicked,
      onState: (name, detail) => onSessionState(slot, name, detail),
    });
    slot.decoder = new FrameDecoder({ keyframe: () => slot.session.keyframe(), failed: (e) => decoderFailed(slot, e) });
    state.sessions.push(slot);
    slot.session.connect();
  }
  updateSplitHandle();
}

function openMessage(slot) {
  const msg = { type: "open", version: PROTOCOL_VERSION, volume: state.volume, settings: settings(slot.mode),
    camera: cameraMessage() };
  if (state.iso !== null) Object.assign(msg, { iso: state.iso, iso_normalized: false });
  return msg;
}

function onReady(slot, index, ready) {
  state.factor = ready.upscale_factor;
  state.limits = ready.limits;
  state.modes = Object.fromEntries(ready.modes.map((m) => [m.name, m]));
  $("bitrate").max = ready.limits.max_bitrate_kbps;
  state.encoders = ready.encoders;
  markEncodings();
  slot.decoder.reset(); // a new session's stream starts with a keyframe
  if (index === 0) {
    state.info = ready.volume;
    if (state.iso === null) state.iso = ready.volume.iso;
    setupIso();
    setupTime(ready.volume.steps);
    setNotice(autoNotice()); // the server's notice, if any, follows
  }
  // Opened before the server's encoders were known: switch to the best of them.
  const wanted = encoding();
  if (wanted !== ready.settings.encoding && ready.encoders.includes(wanted)) {
    slot.session.send({ type: "settings", settings: { encoding: wanted } });
  }
  if (state.modes[slot.mode]?.focus) slot.session.send(focusMessage());
  setBanner("");
}

async function onSessionState(slot, name, detail) {
  if (slot !== state.sessions[0] && name !== "error") return;
  if (name === "open") setConnState("open", "connected");
  else if (name === "connecting") setConnState("connecting", "connecting");
  else if (name === "error") {
    setConnState("error", "error");
    setBanner(`server error ${detail.code}: ${detail.reason}\nchange a setting to try again`);
  } else if (name === "lost") {
    // A denied handshake looks like a lost connection to a browser: ask over HTTP why (the server
    // metadata needs the token; the health probes do not).
    try {
      await getJson("/v2");
    } catch (e) {
      if (e.status === 401 && !slot.session.closed) {
        for (const s of state.sessions) s.session.close();
        return tokenRefused(e);
      }
    }
    if (slot.session.closed) return;
    const seconds = (detail.delayMs / 1000).toFixed(1);
    setConnState("lost", "lost");
    setBanner(`connection lost${detail.reason ? ` (${detail.reason})` : ""}; reconnecting in ${seconds} s ` +
      `(attempt ${detail.attempt})`, "lost");
  }
}

function serverUnreachable(e) {
  if (e.status === 401) return tokenRefused(e);
  setConnState("lost", "lost");
  setBanner(`cannot reach the server: ${e.message}; retrying in 2 s`, "lost");
  setTimeout(start, 2000);
}

function tokenRefused(e) {
  setConnState("error", "token?");
  setBanner(`the server refused the token (${e.message}); enter the right one above`);
  $("token").focus();
}

// ---- frames ------------------------------------------------------------------------------------

async function onFrame(slot, frame, latency) {
  const now = performance.now();
  const st = slot.stats;
  if (st.arrivals.length) st.intervals.push(now - st.arrivals[st.arrivals.length - 1].t);
  if (st.intervals.length > SPARK_FRAMES) st.intervals.shift();
  st.arrivals.push({ t: now, bytes: frame.bytes });
  while (st.arrivals.length && now - st.arrivals[0].t > 1000) st.arrivals.shift();
  if (latency !== null) st.latency = latency;
  st.times = frame.times;
  st.bytes = frame.bytes;
  slot.refined = frame.refined;
  slot.method = frame.method + expectation(frame.choice);
  slot.legend = frame.legend || null;
  slot.codec = frame.codec ? `${frame.encoding} (${frame.codec})` : frame.encoding;
  slot.targetKbps = frame.bitrate_kbps;
  if (frame.device) slot.device = frame.device; // sent when it changed
  if (frame.codec) slot.video = frame.encoding;
  const id = ++slot.frameId;
  const image = await slot.decoder.picture(frame);
  if (!image) return; // a video frame without its keyframe (one is asked for), or a decoder error
  if (id < slot.shownId) return image.close(); // a newer frame was decoded first
  slot.shownId = id;
  if (slot.image) slot.image.close();
  slot.image = image;
  view.dataset.frames = String(Number(view.dataset.frames) + 1);
  view.dataset.mode = frame.mode;
  view.dataset.encoding = frame.encoding;
  view.dataset.t = String(frame.t ?? 0); // the time step shown
  view.dataset.keyframe = String(frame.keyframe);
  draw();
  if (slot === state.sessions[0]) showFrameInfo(slot);
}

function draw() {
  const [a, b] = state.sessions;
  if (!a || !a.image) return;
  if (view.width !== a.image.width || view.height !== a.image.height) {
    view.width = a.image.width;
    view.height = a.image.height;
  }
  ctx.drawImage(a.image, 0, 0);
  const split = b && b.image && b.image.width === a.image.width && b.image.height === a.image.height;
  if (split) {
    const x = Math.round(state.split * view.width);
    ctx.drawImage(b.image, x, 0, view.width - x, view.height, x, 0, view.width - x, view.height);
  }
  view.dataset.split = split ? b.mode : "";
}

/** What auto expects of the method it chose: its PSNR, its time against the session's budget. */
function expectation(choice) {
  if (!choice) return "";
  if (choice.source === "prior") return ` (auto: measuring; budget ${choice.budget_ms.toFixed(1)} ms)`;
  const psnr = choice.psnr_db === null ? "" : `${choice.psnr_db.toFixed(1)} dB, `;
  const ms = choice.ms === null ? "?" : choice.ms.toFixed(1);
  return ` (auto: ${psnr}${ms} of ${choice.budget_ms.toFixed(1)} ms${choice.fits ? "" : ", over budget"})`;
}

function showFrameInfo(slot) {
  const st = slot.stats;
  const seconds = st.arrivals.length > 1 ? (st.arrivals.at(-1).t - st.arrivals[0].t) / 1000 : 0;
  const fps = seconds > 0 ? (st.arrivals.length - 1) / seconds : 0;
  const bits = st.arrivals.reduce((sum, f) => sum + f.bytes, 0) * 8;
  $("stat-method").textContent = slot.method;
  $("stat-fps").textContent = fps.toFixed(1);
  $("stat-latency").textContent = st.latency === null ? "-" : `${st.latency.toFixed(0)} ms`;
  $("stat-times").textContent = Object.entries(st.times)
    .map(([k, v]) => `${k} ${v < 10 ? v.toFixed(1) : v.toFixed(0)}`).join(", ");
  $("stat-bytes").textContent = `${(st.bytes / 1024).toFixed(1)} KiB`;
  $("stat-codec").textContent = slot.codec;
  const target = slot.targetKbps ? ` (target ${(slot.targetKbps / 1000).toFixed(2)})` : "";
  $("stat-rate").textContent = (bits / 1e6).toFixed(2) + target;
  $("stat-volume").textContent = volumeMemory(slot.device);
  const refined = $("refined");
  refined.dataset.refined = String(slot.refined);
  refined.textContent = slot.refined ? "refined" : "interactive";
  view.dataset.refined = String(slot.refined);
  drawSparkline(st.intervals);
  const box = $("legend-box");
  box.hidden = !slot.legend;
  if (slot.legend) {
    drawLegend($("legend"), slot.legend);
    $("legend-lo").textContent = formatNumber(slot.legend.lo);
    $("legend-hi").textContent = formatNumber(slot.legend.hi);
    $("legend-unit").textContent = slot.legend.unit;
  }
  view.dataset.channel = slot.legend ? slot.legend.channel : "shaded";
}

function drawSparkline(values) {
  const c = $("sparkline");
  const g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  if (values.length < 2) return;
  const top = Math.max(...values) * 1.1;
  g.strokeStyle = "#6cf";
  g.beginPath();
  values.forEach((v, i) => {
    const x = (i / (SPARK_FRAMES - 1)) * c.width;
    const y = c.height - (v / top) * c.height;
    if (i === 0) g.moveTo(x, y); else g.lineTo(x, y);
  });
  g.stroke();
  g.fillStyle = "#999";
  g.fillText(`${top.toFixed(0)} ms`, 2, 10);
}

/** The browser could not decode the slot's video: stop asking for it, say so, send the next best. */
function decoderFailed(slot, message) {
  state.decodable.delete(slot.video);
  markEncodings();
  if ($("encoding").value === slot.video) $("encoding").value = "auto";
  setNotice(`this browser failed to decode ${slot.video} (${message}); sending ${encoding()}`);
  sendSettings();
}

/** The volume's device memory and paging, e.g. "1.3 GB resident (sparse, 0.7% of bricks), last page-in 4.3 s". */
function volumeMemory(device) {
  if (!device) return "-";
  const resident = formatBytes(device.resident_bytes);
  if (device.mode === "dense") return `${resident} resident (dense ${device.storage})`;
  const share = (100 * device.bricks_resident / device.bricks_total).toPrecision(2);
  const paged = device.page_ins ? `, last page-in ${device.last_page_in_s.toFixed(1)} s` : "";
  return `${resident} resident (sparse, ${share}% of bricks)${paged}`;
}

function formatBytes(n) {
  const [unit, scale] = n >= 1e9 ? ["GB", 1e9] : n >= 1e6 ? ["MB", 1e6] : ["kB", 1e3];
  return `${(n / scale).toFixed(1)} ${unit}`;
}

function formatNumber(v) {
  return Math.abs(v) >= 1e4 || (Math.abs(v) < 1e-2 && v !== 0) ? v.toExponential(2) : String(+v.toFixed(3));
}

// ---- iso ---------------------------------------------------------------------------------------

function setupIso() {
  const [lo, hi] = state.info.value_range;
  const iso = $("iso");
  const step = hi > lo ? (hi - lo) / 1000 : 1;
  iso.min = lo + step; // strictly inside the value range: the server refuses an iso at its ends
  iso.max = hi - step;
  iso.step = step;
  iso.value = state.iso;
  $("iso-min").textContent = formatNumber(lo);
  $("iso-max").textContent = formatNumber(hi);
  showIso();
}

function showIso() {
  $("iso-value").textContent = state.iso === null ? "" : formatNumber(state.iso);
  const c = $("histogram");
  const g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  const info = state.info;
  if (!info || !info.histogram) return;
  const logs = info.histogram.map((n) => Math.log1p(n));
  const top = Math.max(...logs, 1e-9);
  const w = c.width / logs.length;
  g.fillStyle = "#58708f";
  logs.forEach((v, i) => g.fillRect(i * w, c.height * (1 - v / top), Math.ceil(w), c.height * (v / top)));
  const [lo, hi] = info.value_range;
  const x = hi > lo ? ((state.iso - lo) / (hi - lo)) * c.width : c.width / 2;
  g.fillStyle = "#ffcc33";
  g.fillRect(x - 1, 0, 2, c.height);
}

function setIso(value) {
  if (!state.info) return;
  const [lo, hi] = state.info.value_range;
  const step = (hi - lo) / 1000; // strictly inside the value range, as the slider
  state.iso = Math.min(hi - step, Math.max(lo + step, value));
  $("iso").value = state.iso;
  showIso();
  queue("iso", { type: "iso", value: state.iso, normalized: false });
  if (state.surfaces.length) sendSettings(); // the slider's surface is one of settings.surfaces
}

// ---- time steps ----------------------------------------------------------------------------------

/** Show the time controls for a series (steps > 1) only. */
function setupTime(steps) {
  $("time").hidden = steps <= 1;
  $("step").max = Math.max(0, steps - 1);
  if (steps <= 1) stopPlayback();
  showStep();
}

function showStep() {
  $("step").value = state.step;
  $("step-value").textContent = state.info ? `${state.step} / ${state.info.steps - 1}` : "";
}

function setStep(t) {
  if (!state.info || state.info.steps <= 1) return;
  state.step = ((t % state.info.steps) + state.info.steps) % state.info.steps;
  showStep();
  queue("step", { type: "settings", settings: { t: state.step } });
}

/** Play: the next step every 1/rate s, looping; the server renders the newest step asked (latest
 * wins), so a rate above what it makes skips steps rather than falling behind. */
function togglePlayback() {
  if (state.playing !== null) return stopPlayback();
  const rate = Math.min(60, Math.max(0.1, Number($("rate").value) || 4));
  state.playing = setInterval(() => setStep(state.step + 1), 1000 / rate);
  $("play").textContent = "pause";
}

function stopPlayback() {
  clearInterval(state.playing);
  state.playing = null;
  $("play").textContent = "play";
}

// ---- updates: coalesced to one message of each kind per animation frame --------------------------

function queue(kind, message) {
  state.pending[kind] = message;
  requestAnimationFrame(flush);
}

function flush() {
  const pending = state.pending;
  state.pending = {};
  for (const message of Object.values(pending)) for (const s of state.sessions) s.session.send(message);
}

function sendSettings() {
  if (state.sessions.some((s) => s.session.ready === null)) return openSessions(); // error or not open yet
  for (const s of state.sessions) {
    s.session.send({ type: "settings", settings: settings(s.mode) });
    if (state.modes[s.mode]?.focus) s.session.send(focusMessage());
  }
}

function cameraChanged() {
  $("ruler").toggleAttribute("hidden", true); // its ends were points of the previous view
  $("camera-json").value = JSON.stringify(state.camera);
  queue("camera", cameraMessage());
}

// ---- size --------------------------------------------------------------------------------------

/** Fit the image to the stage: a multiple of the upscale factor within the server's limits. */
function resize(send = true) {
  const stage = $("stage");
  const f = state.factor;
  let w = Math.max(f, Math.floor(stage.clientWidth / f) * f);
  let h = Math.max(f, Math.floor(stage.clientHeight / f) * f);
  if (state.limits) {
    const scale = Math.min(1, state.limits.max_side / Math.max(w, h), Math.sqrt(state.limits.max_pixels / (w * h)));
    w = Math.max(f, Math.floor((w * scale) / f) * f);
    h = Math.max(f, Math.floor((h * scale) / f) * f);
  }
  const changed = w !== state.width || h !== state.height;
  state.width = w;
  state.height = h;
  if (changed && send) sendSettings();
  updateSplitHandle();
}

function updateSplitHandle() {
  const handle = $("split-handle");
  handle.hidden = state.sessions.length < 2;
  handle.style.left = `${state.split * state.width}px`;
  handle.style.height = `${state.height}px`;
  $("lens-row").hidden = !shownFocus();
  $("interpolation-row").hidden = !anyShown((m) => m.options.some((o) => o.name === "interpolation"));
  $("ao-row").hidden = !anyShown((m) => m.options.some((o) => o.name === "ao_rays"));
  const bounds = option(modes()[0], "ao_rays");
  if (bounds) Object.assign($("ao-rays"), { min: bounds.low, max: bounds.high });
  showLens();
}

function showLens() {
  const lens = $("lens");
  const p = state.pointer;
  lens.hidden = !p || !shownFocus();
  if (lens.hidden) return;
  const r = Number($("lens-radius").value);
  Object.assign(lens.style, { left: `${p.x - r}px`, top: `${p.y - r}px`, width: `${2 * r}px`, height: `${2 * r}px` });
}

// ---- camera interaction ------------------------------------------------------------------------

function orbitBy(dYaw, dPitch) {
  const c = state.camera;
  c.yaw = ((c.yaw + dYaw + 540) % 360) - 180;
  c.pitch = Math.min(89, Math.max(-89, c.pitch + dPitch));
  cameraChanged();
}

function zoomBy(factor) {
  state.camera.distance = Math.min(100, Math.max(0.05, state.camera.distance * factor));
  cameraChanged();
}

function resetCamera() {
  state.camera = structuredClone(DEFAULT_CAMERA);
  cameraChanged();
}

/** A camera from JSON text, checked field by field; throws an Error naming what is wrong. */
function parseCamera(text) {
  const c = JSON.parse(text);
  const number = (k, lo, hi) => {
    if (typeof c[k] !== "number" || !Number.isFinite(c[k]) || c[k] < lo || c[k] > hi) {
      throw new Error(`camera.${k} must be a number in [${lo}, ${hi}]`);
    }
    return c[k];
  };
  const target = c.target === undefined ? [0, 0, 0] : c.target;
  if (!Array.isArray(target) || target.length !== 3 || !target.every((v) => Number.isFinite(v) && Math.abs(v) < 1e6)) {
    throw new Error("camera.target must be a list of 3 finite numbers");
  }
  return { yaw: number("yaw", -1e6, 1e6), pitch: number("pitch", -89, 89), distance: number("distance", 1e-6, 1e6),
    target, fov_y: c.fov_y === undefined ? 40 : number("fov_y", 1, 170) };
}

function download(name, blob) {
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob);
  a.download = name;
  a.click();
  setTimeout(() => URL.revokeObjectURL(a.href), 1000);
}

function screenshot() {
  view.toBlob((blob) => download(`isosr-${state.volume}-${Date.now()}.png`, blob), "image/png");
}

/** The isosurface of the current iso, cut by the view's clip, as a PLY mesh file (GET /v1/volumes/NAME/mesh). */
async function saveMesh() {
  if (!state.volume) return;
  const iso = state.iso === null ? "" : `iso=${state.iso}&`;
  const clip = encodeURIComponent(JSON.stringify(clipSettings()));
  setNotice("making the mesh…");
  const response = await fetch(`/v1/volumes/${encodeURIComponent(state.volume)}/mesh?${iso}format=ply&clip=${clip}`,
                               { headers: authHeaders() });
  if (!response.ok) {
    const body = await response.json().catch(() => ({}));
    setNotice(`no mesh: ${body.error || response.statusText}`);
    return;
  }
  setNotice("");
  download(`isosr-${state.volume}.ply`, await response.blob());
}

function canvasPoint(event) {
  const rect = view.getBoundingClientRect();
  return { x: event.clientX - rect.left, y: event.clientY - rect.top };
}

// ---- picking and measuring --------------------------------------------------------------------

/** Ask the (left) session what lies under a canvas point. */
function pickAt(p) {
  const slot = state.sessions[0];
  if (!slot) return;
  state.pendingPick = { id: ++state.pickId, x: p.x, y: p.y, surfaces: surfaceSettings() }; // the view's now
  slot.session.pick(Math.min(state.width - 0.5, p.x), Math.min(state.height - 0.5, p.y), state.pendingPick.id);
}

const fmt = (v) => Number(v).toPrecision(4);

/** The server's answer: the readout, and with two hits their distance and a ruler between them. */
function onPicked(picked) {
  const asked = state.pendingPick;
  if (!asked || picked.id !== asked.id) return; // an older pick's answer
  if (!picked.hit) {
    $("stat-pick").textContent = `no surface at (${Math.round(asked.x)}, ${Math.round(asked.y)})`;
    return;
  }
  state.picks = [...state.picks, { x: asked.x, y: asked.y, picked }].slice(-2);
  const [i, j, k] = picked.voxel;
  let text = `value ${fmt(picked.value)} at voxel (${i}, ${j}, ${k}), (${picked.position.map(fmt).join(", ")})`;
  if (picked.cap) text += " on a cut face";
  const surface = asked.surfaces[picked.surface]; // several surfaces: the one hit (picked.surface indexes them)
  if (surface) text += ` on surface ${picked.surface} (iso ${fmt(surface.iso)})`;
  const ruler = $("ruler");
  ruler.toggleAttribute("hidden", state.picks.length < 2); // an SVG element: the attribute, no .hidden
  if (state.picks.length === 2) {
    const [a, b] = state.picks;
    const d = Math.hypot(...a.picked.position.map((v, n) => v - b.picked.position[n]));
    text += `; ${fmt(d)} from the previous pick`;
    ruler.dataset.distance = d;
    Object.entries({ x1: a.x, y1: a.y, x2: b.x, y2: b.y }).forEach(([key, v]) => $("ruler-line").setAttribute(key, v));
    $("ruler-label").setAttribute("x", (a.x + b.x) / 2);
    $("ruler-label").setAttribute("y", (a.y + b.y) / 2 - 4);
    $("ruler-label").textContent = fmt(d);
  }
  $("stat-pick").textContent = text;
  showSlices(picked.voxel);
}

/** The three orthogonal slices through a voxel, with the iso contour (GET /v1/volumes/NAME/slices/AXIS). */
async function showSlices(voxel) {
  state.slicesAt = voxel;
  if (!state.volume || $("slices").hasAttribute("data-off")) return;
  const iso = state.iso === null ? "" : `&iso=${state.iso}`;
  const name = encodeURIComponent(state.volume);
  await Promise.all(AXES.map(async (axis, n) => {
    const response = await fetch(`/v1/volumes/${name}/slices/${axis}?index=${voxel[n]}${iso}`, { headers: authHeaders() });
    if (!response.ok) return;
    const blob = await response.blob();
    if (state.slicesAt !== voxel) return; // a later pick's slices replace these
    const img = $(`slice-${axis}`);
    URL.revokeObjectURL(img.src);
    img.src = URL.createObjectURL(blob);
  }));
  // Shown once loaded, unless the strip was turned off or a later pick took over meanwhile.
  $("slices").hidden = state.slicesAt !== voxel || $("slices").hasAttribute("data-off");
}

/** The slice strip on (at the last pick) or off. */
function toggleSlices() {
  const strip = $("slices");
  strip.toggleAttribute("data-off");
  strip.hidden = true;
  if (!strip.hasAttribute("data-off") && state.slicesAt) showSlices(state.slicesAt);
}

function bindPointer() {
  let drag = null;
  view.addEventListener("pointerdown", (e) => {
    const p = canvasPoint(e);
    drag = { x: e.clientX, y: e.clientY, downX: e.clientX, downY: e.clientY };
    view.setPointerCapture(e.pointerId);
    state.pointer = p;
  });
  view.addEventListener("pointermove", (e) => {
    state.pointer = canvasPoint(e);
    if (drag) {
      orbitBy(-(e.clientX - drag.x) * 0.4, (e.clientY - drag.y) * 0.4);
      drag = { ...drag, x: e.clientX, y: e.clientY };
    } else if (shownFocus()) {
      queue("focus", focusMessage());
    }
    showLens();
  });
  view.addEventListener("pointerup", (e) => {
    const still = drag && Math.hypot(e.clientX - drag.downX, e.clientY - drag.downY) < 3;
    drag = null;
    if (still) pickAt(canvasPoint(e)); // a click, not a drag: what lies there
  });
  view.addEventListener("wheel", (e) => {
    e.preventDefault();
    zoomBy(Math.exp(e.deltaY * 0.001));
  }, { passive: false });
  view.addEventListener("dblclick", resetCamera);

  const handle = $("split-handle");
  handle.addEventListener("pointerdown", (e) => handle.setPointerCapture(e.pointerId));
  handle.addEventListener("pointermove", (e) => {
    if (!handle.hasPointerCapture(e.pointerId)) return;
    state.split = Math.min(1, Math.max(0, canvasPoint(e).x / state.width));
    updateSplitHandle();
    draw();
  });
}

function bindKeys() {
  document.addEventListener("keydown", (e) => {
    if (e.target.matches("input, textarea, select") || e.ctrlKey || e.metaKey || e.altKey) return;
    const step = state.info ? (state.info.value_range[1] - state.info.value_range[0]) / 100 : 0;
    const actions = {
      ArrowLeft: () => orbitBy(5, 0), ArrowRight: () => orbitBy(-5, 0),
      ArrowUp: () => orbitBy(0, 5), ArrowDown: () => orbitBy(0, -5),
      "+": () => zoomBy(0.9), "=": () => zoomBy(0.9), "-": () => zoomBy(1 / 0.9),
      "[": () => setIso(state.iso - step), "]": () => setIso(state.iso + step),
      c: () => cycleChannel(1), C: () => cycleChannel(-1),
      a: () => { $("ao-rays").value = Number($("ao-rays").value) > 0 ? 0 : 1; sendSettings(); },
      s: () => { $("split").checked = !$("split").checked; openSessions(); },
      v: toggleSlices,
      x: cycleClip, X: () => { state.clipFlip = !state.clipFlip; sendSettings(); },
      ",": () => moveClip(-0.02), ".": () => moveClip(0.02),
      r: resetCamera, p: screenshot, t: togglePlayback,
    };
    const picked = /^[1-9]$/.test(e.key) && $("mode").options[Number(e.key) - 1];
    const action = picked ? () => { $("mode").value = picked.value; modeChanged(); } : actions[e.key];
    if (!action) return;
    e.preventDefault();
    action();
  });
}

function cycleChannel(delta) {
  const i = CHANNELS.indexOf($("channel").value);
  $("channel").value = CHANNELS[(i + delta + CHANNELS.length) % CHANNELS.length];
  channelChanged();
}

function channelChanged() {
  // The AO channel of a full-res render needs AO rays.
  if ($("channel").value === "ao" && Number($("ao-rays").value) === 0) $("ao-rays").value = 1;
  sendSettings();
}

/** The AO control at the left mode's starting rays (the server's default for it). */
function aoDefault() {
  const bounds = option(modes()[0], "ao_rays");
  if (bounds) $("ao-rays").value = bounds.default;
}

function modeChanged() {
  aoDefault();
  const shown = modes();
  if (state.sessions.length !== shown.length) return openSessions();
  state.sessions.forEach((s, i) => { s.mode = shown[i]; });
  updateSplitHandle();
  sendSettings();
}

function bindControls() {
  $("token").value = state.token;
  $("token-apply").addEventListener("click", () => {
    state.token = $("token").value.trim();
    if (state.token) sessionStorage.setItem(TOKEN_KEY, state.token);
    else sessionStorage.removeItem(TOKEN_KEY);
    start();
  });
  $("volume").addEventListener("change", () => {
    state.volume = $("volume").value;
    state.iso = null;
    state.surfaces = []; // isos of another volume
    showSurfaces();
    state.info = null;
    state.step = 0;
    stopPlayback();
    openSessions();
  });
  $("step").addEventListener("input", () => setStep(Number($("step").value)));
  $("play").addEventListener("click", togglePlayback);
  $("rate").addEventListener("change", () => { if (state.playing !== null) { stopPlayback(); togglePlayback(); } });
  $("iso").addEventListener("input", () => setIso(Number($("iso").value)));
  $("mode").addEventListener("change", modeChanged);
  $("mode-b").addEventListener("change", modeChanged);
  $("split").addEventListener("change", () => openSessions());
  $("channel").addEventListener("change", channelChanged);
  $("ao-rays").addEventListener("change", sendSettings);
  $("interpolation").addEventListener("change", sendSettings);
  $("encoding").addEventListener("change", () => { setNotice(autoNotice()); sendSettings(); });
  $("bitrate").addEventListener("change", sendSettings);
  $("refine").addEventListener("change", sendSettings);
  $("clip-axis").addEventListener("change", sendSettings);
  $("cap").addEventListener("change", sendSettings);
  $("clip-offset").addEventListener("input", sendSettings);
  $("surface-add").addEventListener("click", addSurface);
  $("surface-clear").addEventListener("click", () => { state.surfaces = []; showSurfaces(); sendSettings(); });
  for (const axis of AXES) {
    $(`crop-${axis}-lo`).addEventListener("input", sendSettings);
    $(`crop-${axis}-hi`).addEventListener("input", sendSettings);
  }
  $("color-by").addEventListener("change", sendSettings);
  $("colormap").addEventListener("change", sendSettings);
  $("color-field").addEventListener("change", sendSettings);
  $("lens-radius").addEventListener("input", () => { showLens(); queue("focus", focusMessage()); });
  $("camera-reset").addEventListener("click", resetCamera);
  $("camera-save").addEventListener("click", () => {
    const text = JSON.stringify(state.camera, null, 1);
    $("camera-json").value = text;
    download("camera.json", new Blob([text], { type: "application/json" }));
  });
  $("camera-apply").addEventListener("click", () => {
    try {
      state.camera = parseCamera($("camera-json").value);
      setBanner("");
      cameraChanged();
    } catch (e) {
      setBanner(`cannot use that camera: ${e.message}`);
    }
  });
  $("screenshot").addEventListener("click", screenshot);
  $("mesh").addEventListener("click", saveMesh);
  let timer = null;
  window.addEventListener("resize", () => { clearTimeout(timer); timer = setTimeout(resize, 150); });
}

// ---- start -------------------------------------------------------------------------------------

async function start() {
  setConnState("connecting", "connecting");
  state.decodable = await decodableEncodings();
  markEncodings();
  let listing;
  try {
    listing = await getJson("/v1/volumes");
  } catch (e) {
    return serverUnreachable(e);
  }
  const names = listing.volumes.map((v) => v.name);
  const asked = new URLSearchParams(location.search).get("volume");
  if (asked && !names.includes(asked)) names.push(asked);
  const select = $("volume");
  select.replaceChildren(...names.map((n) => new Option(n, n)));
  state.volume = names.includes(state.volume) ? state.volume : asked || names[0] || null;
  select.value = state.volume;
  if (!state.volume) return setBanner("the server offers no volumes");
  setBanner("");
  openSessions();
}

bindControls();
bindPointer();
bindKeys();
$("camera-json").value = JSON.stringify(state.camera);
start();
