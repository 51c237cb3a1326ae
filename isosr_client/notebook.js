// The notebook widget's browser side (anywidget): one view session on the server at `url`, drawn on a
// canvas. The session and frame decoding are the viewer page's own modules, imported from that server,
// so the widget speaks the protocol version of the server it talks to.
// Python sets iso, camera, mode, size, t or encoding: the session sends them; a drag or the wheel here
// sets `camera` (and so Python's); the session's state lands in `status`, the volume's info in `info`.

const SETTINGS = ["mode", "width", "height", "t", "encoding"];

function render({ model, el }) {
  const canvas = document.createElement("canvas");
  canvas.className = "isosr-widget-view";
  Object.assign(canvas.style, { cursor: "grab", touchAction: "none", background: "#000", display: "block" });
  const status = document.createElement("div");
  status.className = "isosr-widget-status";
  Object.assign(status.style, { font: "12px monospace", minHeight: "1.2em" });
  el.append(canvas, status);
  canvas.dataset.frames = "0";
  let session = null;
  let decoder = null;
  let sentIso = null; // the iso the session has: the ready's suggestion needs no iso message back
  let generation = 0;

  function setStatus(text) {
    status.textContent = text;
    model.set("status", text);
    model.save_changes();
  }

  const settings = () => Object.fromEntries(SETTINGS.map((k) => [k, model.get(k)]));

  async function connect() {
    session?.close();
    session = null;
    const mine = ++generation;
    const base = model.get("url").replace(/\/+$/, "");
    let modules;
    try {
      modules = await Promise.all([import(`${base}/static/session.js`), import(`${base}/static/video.js`)]);
    } catch (e) {
      return setStatus(`error: cannot load the viewer's modules from ${base}: ${e.message}`);
    }
    if (mine !== generation) return; // a later connect() superseded this one
    const [{ ViewSession, PROTOCOL_VERSION }, { FrameDecoder }] = modules;
    const open = () => {
      const iso = model.get("iso");
      sentIso = iso;
      return { type: "open", version: PROTOCOL_VERSION, volume: model.get("volume"), settings: settings(),
        camera: { type: "camera", ...model.get("camera") }, ...(iso === null ? {} : { iso, iso_normalized: false }) };
    };
    const wsUrl = base.replace(/^http/, "ws") + "/v1/view";
    const s = new ViewSession(wsUrl, model.get("token"), open, {
      onReady(ready) {
        model.set("info", ready.volume);
        if (model.get("iso") === null) {
          sentIso = ready.volume.iso;
          model.set("iso", ready.volume.iso);
        }
        model.save_changes();
      },
      async onFrame(frame) {
        const image = await decoder.picture(frame);
        if (!image) return; // a video frame without its keyframe (one is asked for)
        canvas.width = image.width;
        canvas.height = image.height;
        canvas.getContext("2d").drawImage(image, 0, 0);
        image.close();
        canvas.dataset.frames = String(Number(canvas.dataset.frames) + 1);
        canvas.dataset.t = String(frame.t ?? 0);
      },
      onNotice: (text) => setStatus(`notice: ${text}`),
      onState(name, detail) {
        if (name === "error") setStatus(`error ${detail.code}: ${detail.reason}`);
        else if (name === "lost") setStatus(`lost (${detail.reason || detail.code}); reconnecting`);
        else setStatus(name);
      },
    });
    decoder = new FrameDecoder({ keyframe: () => s.keyframe(), failed: (e) => setStatus(`decoder: ${e}`) });
    session = s;
    s.connect();
  }

  model.on("change:iso", () => {
    const iso = model.get("iso");
    if (iso === null || iso === sentIso) return;
    sentIso = iso;
    session?.send({ type: "iso", value: iso, normalized: false });
  });
  model.on("change:camera", () => session?.send({ type: "camera", ...model.get("camera") }));
  for (const k of SETTINGS) {
    model.on(`change:${k}`, () => session?.send({ type: "settings", settings: { [k]: model.get(k) } }));
  }
  for (const k of ["url", "token", "volume"]) model.on(`change:${k}`, connect);

  // Orbit on a drag, zoom on the wheel, as the viewer page does.
  let drag = null;
  const setCamera = (change) => {
    model.set("camera", { ...model.get("camera"), ...change });
    model.save_changes();
  };
  canvas.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const c = model.get("camera");
    setCamera({ yaw: ((c.yaw - (e.clientX - drag.x) * 0.4 + 540) % 360) - 180,
      pitch: Math.min(89, Math.max(-89, c.pitch + (e.clientY - drag.y) * 0.4)) });
    drag = { x: e.clientX, y: e.clientY };
  });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    setCamera({ distance: Math.min(100, Math.max(0.05, model.get("camera").distance * Math.exp(e.deltaY * 0.001))) });
  }, { passive: false });

  connect();
  return () => {
    generation += 1;
    session?.close();
  };
}

export default { render };
