// dbb-stream/1 (docs/protocol.md): the websocket, view requests, frame headers, reconnection.

export const REQUEST_BYTES = 112;
export const HEADER_BYTES = 128;
export const FORMAT_JPEG = 0;      // colour JPEG + alpha greyscale PNG
export const FORMAT_PNG = 1;       // one RGBA PNG
export const FORMAT_RAW = 2;       // the straight RGBA bytes (nothing to decode)
export const FORMAT_NAMES = { [FORMAT_JPEG]: 'jpeg', [FORMAT_PNG]: 'png', [FORMAT_RAW]: 'raw' };

/** A 112-byte view request. `c2w`: 16 numbers, camera-to-world, row-major, OpenGL axes. */
export function packRequest({ seq, clientMs, object, eye = 0, lossless = false, raw = false, c2w, fovYDeg = 0,
                              fx = 0, fy = 0, cx = 0, cy = 0, viewportW = 0, viewportH = 0, sizePx = 0 }) {
  const buf = new ArrayBuffer(REQUEST_BYTES);
  const v = new DataView(buf);
  v.setUint8(0, 0x44); v.setUint8(1, 0x42); v.setUint8(2, 0x42); v.setUint8(3, 0x51);   // "DBBQ"
  v.setUint32(4, seq >>> 0, true);
  v.setFloat64(8, clientMs, true);
  v.setUint16(16, object, true);
  v.setUint8(18, eye);
  v.setUint8(19, (lossless ? 1 : 0) | (raw ? 2 : 0));
  for (let i = 0; i < 16; i++) v.setFloat32(20 + 4 * i, c2w[i], true);
  v.setFloat32(84, fovYDeg, true);
  v.setFloat32(88, fx, true); v.setFloat32(92, fy, true);
  v.setFloat32(96, cx, true); v.setFloat32(100, cy, true);
  v.setUint16(104, clamp16(viewportW), true); v.setUint16(106, clamp16(viewportH), true);
  v.setUint16(108, clamp16(sizePx), true);
  v.setUint16(110, 0, true);
  return buf;
}

function clamp16(x) { return Math.max(0, Math.min(65535, Math.round(x))); }

/** The 128-byte header of a frame message. */
export function parseFrameHeader(buf) {
  const v = new DataView(buf);
  const magic = String.fromCharCode(v.getUint8(0), v.getUint8(1), v.getUint8(2), v.getUint8(3));
  if (magic !== 'DBBF' || buf.byteLength < HEADER_BYTES) throw new Error(`not a frame (${magic})`);
  const c2w = [];
  for (let i = 0; i < 16; i++) c2w.push(v.getFloat32(32 + 4 * i, true));
  return {
    seq: v.getUint32(4, true), clientMs: v.getFloat64(8, true), object: v.getUint16(16, true),
    eye: v.getUint8(18), format: v.getUint8(19), serverMs: v.getFloat64(20, true),
    renderMs: v.getFloat32(28, true), c2w,
    centre: [v.getFloat32(96, true), v.getFloat32(100, true), v.getFloat32(104, true)],
    sideM: v.getFloat32(108, true), width: v.getUint16(112, true), height: v.getUint16(114, true),
    step: v.getUint32(116, true), colourBytes: v.getUint32(120, true), alphaBytes: v.getUint32(124, true),
  };
}

/**
 * One websocket to dbb-serve that reconnects by itself with exponential backoff.
 * Callbacks: onHello(hello), onFrame(header, buffer, receivedMs), onMessage(json), onStatus(status, detail).
 */
export class Stream {
  constructor(url, handlers) {
    this.url = url;
    this.h = handlers;
    this.ws = null;
    this.status = 'connecting';
    this.connects = 0;
    this.backoffMs = 250;
    this.seq = 0;
    this.closed = false;
    this._timer = null;
    this.open();
  }

  get isOpen() { return this.ws !== null && this.ws.readyState === WebSocket.OPEN && this.status === 'connected'; }

  open() {
    if (this.closed) return;
    this._setStatus('connecting');
    let ws;
    try {
      ws = new WebSocket(this.url);
    } catch (e) {
      this._retry(String(e));
      return;
    }
    ws.binaryType = 'arraybuffer';
    this.ws = ws;
    ws.onmessage = (ev) => {
      if (typeof ev.data === 'string') {
        let msg;
        try { msg = JSON.parse(ev.data); } catch { return; }
        if (msg.type === 'hello') {
          this.connects += 1;
          this.backoffMs = 250;
          this._setStatus('connected');
          this.h.onHello?.(msg);
        } else {
          this.h.onMessage?.(msg);
        }
      } else {
        this.h.onFrame?.(ev.data, performance.now());
      }
    };
    ws.onclose = () => {
      if (this.ws !== ws) return;
      this.ws = null;
      this._retry('the connection closed');
    };
    ws.onerror = () => {};           // onclose follows; the retry is scheduled there
  }

  _retry(why) {
    if (this.closed) return;
    const wait = this.backoffMs;
    this.backoffMs = Math.min(4000, this.backoffMs * 2);
    this.retryAt = performance.now() + wait;
    this._setStatus('disconnected', why);
    clearTimeout(this._timer);
    this._timer = setTimeout(() => this.open(), wait);
  }

  _setStatus(s, detail = '') {
    this.status = s;
    this.h.onStatus?.(s, detail);
  }

  nextSeq() { this.seq = (this.seq + 1) >>> 0; return this.seq; }

  send(data) {
    if (!this.isOpen) return false;
    this.ws.send(data);
    return true;
  }

  control(msg) { return this.send(JSON.stringify(msg)); }

  close() {
    this.closed = true;
    clearTimeout(this._timer);
    this.ws?.close();
  }
}
