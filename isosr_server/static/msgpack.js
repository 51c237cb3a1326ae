// msgpack for the isosr wire protocol: nil, bool, integers, float32/64, str, bin, array, map.
// Extension types are not part of the protocol and are refused, as the server refuses them.

const textEncoder = new TextEncoder();
const textDecoder = new TextDecoder("utf-8", { fatal: true });

/** Encode a value: null, boolean, number, string, Uint8Array (bin), Array, plain object (map). */
export function encode(value) {
  const out = new Writer();
  out.value(value);
  return out.bytes();
}

/** Decode one msgpack value; throws on truncated data, trailing bytes or extension types. */
export function decode(buffer) {
  const bytes = buffer instanceof Uint8Array ? buffer : new Uint8Array(buffer);
  const reader = new Reader(bytes);
  const value = reader.value();
  if (reader.pos !== bytes.length) throw new Error("msgpack: bytes after the value");
  return value;
}

class Writer {
  constructor() {
    this.buf = new Uint8Array(256);
    this.view = new DataView(this.buf.buffer);
    this.pos = 0;
  }

  reserve(n) {
    if (this.pos + n <= this.buf.length) return;
    const bigger = new Uint8Array(Math.max(this.buf.length * 2, this.pos + n));
    bigger.set(this.buf);
    this.buf = bigger;
    this.view = new DataView(bigger.buffer);
  }

  u8(v) { this.reserve(1); this.view.setUint8(this.pos, v); this.pos += 1; }
  u16(v) { this.reserve(2); this.view.setUint16(this.pos, v); this.pos += 2; }
  u32(v) { this.reserve(4); this.view.setUint32(this.pos, v); this.pos += 4; }
  raw(bytes) { this.reserve(bytes.length); this.buf.set(bytes, this.pos); this.pos += bytes.length; }

  value(v) {
    if (v === null || v === undefined) this.u8(0xc0);
    else if (v === false) this.u8(0xc2);
    else if (v === true) this.u8(0xc3);
    else if (typeof v === "number") this.number(v);
    else if (typeof v === "string") this.string(v);
    else if (v instanceof Uint8Array) this.bin(v);
    else if (Array.isArray(v)) this.array(v);
    else if (typeof v === "object") this.map(v);
    else throw new Error(`msgpack: cannot encode ${typeof v}`);
  }

  number(v) {
    if (Number.isSafeInteger(v)) this.integer(v);
    else {
      this.reserve(9);
      this.view.setUint8(this.pos, 0xcb);
      this.view.setFloat64(this.pos + 1, v);
      this.pos += 9;
    }
  }

  integer(v) {
    if (v >= 0) {
      if (v < 0x80) this.u8(v);
      else if (v < 0x100) { this.u8(0xcc); this.u8(v); }
      else if (v < 0x10000) { this.u8(0xcd); this.u16(v); }
      else if (v < 0x100000000) { this.u8(0xce); this.u32(v); }
      else { this.u8(0xcf); this.u32(Math.floor(v / 0x100000000)); this.u32(v >>> 0); }
    } else if (v >= -32) this.u8(v & 0xff);
    else if (v >= -0x80) { this.u8(0xd0); this.u8(v & 0xff); }
    else if (v >= -0x8000) { this.u8(0xd1); this.u16(v & 0xffff); }
    else if (v >= -0x80000000) { this.u8(0xd2); this.u32(v >>> 0); }
    else { this.u8(0xd3); this.u32(Math.floor(v / 0x100000000) >>> 0); this.u32(v >>> 0); }
  }

  string(s) {
    const bytes = textEncoder.encode(s);
    const n = bytes.length;
    if (n < 32) this.u8(0xa0 | n);
    else if (n < 0x100) { this.u8(0xd9); this.u8(n); }
    else if (n < 0x10000) { this.u8(0xda); this.u16(n); }
    else { this.u8(0xdb); this.u32(n); }
    this.raw(bytes);
  }

  bin(bytes) {
    const n = bytes.length;
    if (n < 0x100) { this.u8(0xc4); this.u8(n); }
    else if (n < 0x10000) { this.u8(0xc5); this.u16(n); }
    else { this.u8(0xc6); this.u32(n); }
    this.raw(bytes);
  }

  array(a) {
    this.header(a.length, 0x90, 0xdc);
    for (const item of a) this.value(item);
  }

  map(o) {
    const keys = Object.keys(o).filter((k) => o[k] !== undefined);
    this.header(keys.length, 0x80, 0xde);
    for (const k of keys) { this.string(k); this.value(o[k]); }
  }

  header(n, fix, code16) {
    if (n < 16) this.u8(fix | n);
    else if (n < 0x10000) { this.u8(code16); this.u16(n); }
    else { this.u8(code16 + 1); this.u32(n); }
  }

  bytes() { return this.buf.slice(0, this.pos); }
}

class Reader {
  constructor(bytes) {
    this.bytes = bytes;
    this.view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    this.pos = 0;
  }

  need(n) {
    if (this.pos + n > this.bytes.length) throw new Error("msgpack: truncated data");
    const at = this.pos;
    this.pos += n;
    return at;
  }

  u8() { return this.view.getUint8(this.need(1)); }
  u16() { return this.view.getUint16(this.need(2)); }
  u32() { return this.view.getUint32(this.need(4)); }

  value() {
    const c = this.u8();
    if (c < 0x80) return c;
    if (c >= 0xe0) return c - 0x100;
    if ((c & 0xf0) === 0x80) return this.map(c & 0x0f);
    if ((c & 0xf0) === 0x90) return this.array(c & 0x0f);
    if ((c & 0xe0) === 0xa0) return this.string(c & 0x1f);
    switch (c) {
      case 0xc0: return null;
      case 0xc2: return false;
      case 0xc3: return true;
      case 0xc4: return this.bin(this.u8());
      case 0xc5: return this.bin(this.u16());
      case 0xc6: return this.bin(this.u32());
      case 0xca: return this.view.getFloat32(this.need(4));
      case 0xcb: return this.view.getFloat64(this.need(8));
      case 0xcc: return this.u8();
      case 0xcd: return this.u16();
      case 0xce: return this.u32();
      case 0xcf: { const hi = this.u32(); return hi * 0x100000000 + this.u32(); }
      case 0xd0: return this.view.getInt8(this.need(1));
      case 0xd1: return this.view.getInt16(this.need(2));
      case 0xd2: return this.view.getInt32(this.need(4));
      case 0xd3: { const hi = this.view.getInt32(this.need(4)); return hi * 0x100000000 + this.u32(); }
      case 0xd9: return this.string(this.u8());
      case 0xda: return this.string(this.u16());
      case 0xdb: return this.string(this.u32());
      case 0xdc: return this.array(this.u16());
      case 0xdd: return this.array(this.u32());
      case 0xde: return this.map(this.u16());
      case 0xdf: return this.map(this.u32());
      default: throw new Error(`msgpack: type 0x${c.toString(16)} is not part of the protocol`);
    }
  }

  string(n) { const at = this.need(n); return textDecoder.decode(this.bytes.subarray(at, at + n)); }
  bin(n) { const at = this.need(n); return this.bytes.slice(at, at + n); }

  array(n) {
    const a = new Array(n);
    for (let i = 0; i < n; i++) a[i] = this.value();
    return a;
  }

  map(n) {
    const o = {};
    for (let i = 0; i < n; i++) {
      const k = this.value();
      if (typeof k !== "string") throw new Error("msgpack: map keys must be strings");
      o[k] = this.value();
    }
    return o;
  }
}
