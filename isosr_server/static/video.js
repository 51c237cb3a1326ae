// Frames to pictures: image frames through the browser's image decoder, video frames (h264, vp9,
// av1: one access unit each) through WebCodecs' VideoDecoder. WebCodecs exists only in secure
// contexts (https, or loopback).

// Video encodings, best first, with a codec string the browser is asked about (1080p levels);
// the frames name their stream's own string.
export const VIDEO_PROBES = { av1: "av01.0.08M.08", vp9: "vp09.00.40.08", h264: "avc1.640028" };
export const IMAGE_ENCODINGS = ["jpeg", "png", "webp"];
// A decoder that fails this often in a row gives the encoding up (the page falls back to jpeg).
const MAX_DECODER_ERRORS = 3;
// A video frame the decoder has not put out after this long is given up (its ack must not wait forever).
const STALL_MS = 1000;

/** The encodings this browser can show: the images, and the video codecs its VideoDecoder supports. */
export async function decodableEncodings() {
  const found = new Set(IMAGE_ENCODINGS);
  if (typeof VideoDecoder === "undefined") return found;
  for (const [encoding, codec] of Object.entries(VIDEO_PROBES)) {
    const { supported } = await VideoDecoder.isConfigSupported({ codec, optimizeForLatency: true }).catch(() => ({}));
    if (supported) found.add(encoding);
  }
  return found;
}

/**
 * One view session's decoding. hooks: keyframe() (ask the server for one: after a decoder error,
 * or a delta frame with no keyframe before it), failed(message) (the decoder failed
 * MAX_DECODER_ERRORS times in a row: stop asking for this encoding).
 */
export class FrameDecoder {
  constructor(hooks) {
    this.hooks = hooks;
    this.decoder = null;
    this.codec = null;
    this.pending = new Map(); // timestamp_us -> {frame, resolve}
    this.needKey = true;
    this.asked = false;
    this.errors = 0;
  }

  /** The frame's picture, an ImageBitmap of frame.width x frame.height (null: none to show). */
  picture(frame) {
    if (!(frame.encoding in VIDEO_PROBES)) {
      return createImageBitmap(new Blob([frame.image], { type: `image/${frame.encoding}` }));
    }
    if (frame.keyframe) {
      if (frame.codec !== this.codec) this.configure(frame.codec);
      this.needKey = false;
    }
    if (this.needKey || !this.decoder) {
      this.askKeyframe();
      return Promise.resolve(null);
    }
    const timestamp = frame.timestamp_us;
    return new Promise((resolve) => {
      this.pending.set(timestamp, { frame, resolve });
      setTimeout(() => this.give(timestamp, null), STALL_MS);
      try {
        this.decoder.decode(new EncodedVideoChunk({ type: frame.keyframe ? "key" : "delta", timestamp,
          data: frame.image }));
      } catch (e) {
        this.failed(e);
      }
    });
  }

  configure(codec) {
    this.reset();
    this.codec = codec;
    try {
      this.decoder = new VideoDecoder({ output: (videoFrame) => this.output(videoFrame), error: (e) => this.failed(e) });
      this.decoder.configure({ codec, optimizeForLatency: true });
    } catch (e) {
      this.failed(e);
    }
  }

  /** A decoded picture: cut to the frame's size (video is coded at even sides), then the VideoFrame is closed. */
  output(videoFrame) {
    this.errors = 0;
    const timestamp = videoFrame.timestamp;
    for (const t of this.pending.keys()) if (t < timestamp) this.give(t, null); // the decoder dropped these
    const entry = this.pending.get(timestamp);
    if (!entry) return videoFrame.close();
    createImageBitmap(videoFrame, 0, 0, entry.frame.width, entry.frame.height)
      .then((image) => this.give(timestamp, image), () => this.give(timestamp, null))
      .finally(() => videoFrame.close());
  }

  give(timestamp, image) {
    const entry = this.pending.get(timestamp);
    this.pending.delete(timestamp);
    if (entry) entry.resolve(image);
    else if (image) image.close();
  }

  failed(error) {
    this.reset();
    this.errors += 1;
    if (this.errors >= MAX_DECODER_ERRORS) this.hooks.failed(error.message || String(error));
    else this.askKeyframe();
  }

  askKeyframe() {
    if (this.asked) return;
    this.asked = true;
    this.hooks.keyframe();
  }

  /** Forget the stream (a new session, an error): the next video frame must be a keyframe. */
  reset() {
    if (this.decoder && this.decoder.state !== "closed") this.decoder.close();
    this.decoder = null;
    this.codec = null;
    this.needKey = true;
    this.asked = false;
    for (const t of [...this.pending.keys()]) this.give(t, null);
  }
}
