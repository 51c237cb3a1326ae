// One view session (WS /v1/view): open, latest-wins updates, frames acknowledged once shown (flow
// control: the server makes the next frame only on credit), errors, reconnect with backoff.
import { decode, encode } from "./msgpack.js";

export const PROTOCOL_VERSION = 12;
const SUBPROTOCOL = "isosr.v1";
const TOKEN_SUBPROTOCOL_PREFIX = "isosr-token.";
// Close codes after which reconnecting would only repeat the client's mistake.
const CLIENT_FAULTS = new Set([1007, 1008, 1009, 4401, 4404]);
const BACKOFF_MS = [500, 1000, 2000, 4000, 8000];

/** Subprotocols carrying the token (browsers cannot set headers on a WebSocket; URLs get logged). */
export function subprotocols(token) {
  return token ? [SUBPROTOCOL, TOKEN_SUBPROTOCOL_PREFIX + token] : [SUBPROTOCOL];
}

/**
 * A view session that reopens itself after a lost connection.
 * hooks: onReady(ready), onFrame(frame, latencyMs) (may return a promise: the frame is acknowledged
 * once it settles), onNotice(text) (the server's non-fatal news), onPicked(picked) (the answer to pick),
 * onState(state, detail) with state one of
 * "connecting", "open", "lost" (detail: {attempt, delayMs}), "error" (detail: {code, reason}).
 * openMessage(): the current `open` message (volume, settings, camera, iso), built by the page.
 */
export class ViewSession {
  constructor(wsUrl, token, openMessage, hooks) {
    this.wsUrl = wsUrl;
    this.token = token;
    this.openMessage = openMessage;
    this.hooks = hooks;
    this.ws = null;
    this.seq = 0;
    this.sentAt = new Map();
    this.attempt = 0;
    this.timer = null;
    this.closed = false;
    this.ready = null;
    this.lastAck = -1;
  }

  connect() {
    clearTimeout(this.timer);
    this.ready = null;
    this.lastAck = -1;
    this.sentAt.clear();
    this.hooks.onState("connecting", {});
    let ws;
    try {
      ws = new WebSocket(this.wsUrl, subprotocols(this.token));
    } catch (e) {
      this.fail(0, `cannot open the WebSocket: ${e.message}`);
      return;
    }
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    let serverError = null;
    ws.onopen = () => ws.send(encode(this.openMessage()));
    ws.onmessage = (event) => {
      if (this.ws !== ws) return; // a message that crossed close()
      let msg;
      try {
        msg = decode(event.data);
      } catch (e) {
        this.fail(1007, `unreadable server message: ${e.message}`);
        return;
      }
      if (msg.type === "ready") {
        this.ready = msg;
        this.attempt = 0;
        this.hooks.onState("open", {});
        this.hooks.onReady(msg);
      } else if (msg.type === "frame") {
        // Acknowledged once decoded and drawn (or failed to), so frames come as fast as they are shown.
        Promise.resolve()
          .then(() => this.hooks.onFrame(msg, this.latency(msg.ack)))
          .finally(() => this.acknowledge(ws, msg.seq));
      } else if (msg.type === "notice") {
        this.hooks.onNotice(msg.text);
      } else if (msg.type === "picked") {
        this.hooks.onPicked?.(msg);
      } else if (msg.type === "error") {
        serverError = msg;
      }
    };
    ws.onclose = (event) => {
      if (this.ws !== ws || this.closed) return;
      this.ws = null;
      const code = serverError ? serverError.code : event.code;
      const reason = serverError ? serverError.reason : event.reason;
      if (serverError && CLIENT_FAULTS.has(code)) this.fail(code, reason);
      else this.lost(code, reason);
    };
  }

  /** Milliseconds since the client message the frame acknowledges was sent (null: none new). */
  latency(ack) {
    if (ack <= this.lastAck) return null;
    this.lastAck = ack;
    const sent = this.sentAt.get(ack);
    for (const k of this.sentAt.keys()) if (k <= ack) this.sentAt.delete(k);
    return sent === undefined ? null : performance.now() - sent;
  }

  /** Tell the server frame `seq` was shown: credit for the next (not on a newer connection). */
  acknowledge(ws, seq) {
    if (this.ws === ws && ws.readyState === WebSocket.OPEN) ws.send(encode({ type: "received", frame: seq }));
  }

  lost(code, reason) {
    const delayMs = BACKOFF_MS[Math.min(this.attempt, BACKOFF_MS.length - 1)];
    this.attempt += 1;
    this.hooks.onState("lost", { attempt: this.attempt, delayMs, code, reason });
    this.timer = setTimeout(() => this.connect(), delayMs);
  }

  fail(code, reason) {
    this.hooks.onState("error", { code, reason });
  }

  /** Send a camera / iso / settings / focus message (dropped while not open; `open` carries the state). */
  send(message) {
    if (!this.ws || this.ws.readyState !== WebSocket.OPEN || !this.ready) return;
    const seq = this.seq++;
    this.sentAt.set(seq, performance.now());
    this.ws.send(encode({ ...message, seq }));
  }

  /** Ask what lies under pixel (x, y) of the current view; `onPicked` gets the answer with this id. */
  pick(x, y, id) {
    if (!this.ws || this.ws.readyState !== WebSocket.OPEN || !this.ready) return;
    this.ws.send(encode({ type: "pick", x, y, id }));
  }

  /** Ask for a keyframe (the next video frame decodes alone). */
  keyframe() {
    if (this.ws && this.ws.readyState === WebSocket.OPEN && this.ready) this.ws.send(encode({ type: "keyframe" }));
  }

  close() {
    this.closed = true;
    clearTimeout(this.timer);
    if (this.ws) this.ws.close(1000);
    this.ws = null;
  }
}
