// The decoding worker: {id, buffer, head} in, {id, rgba, hash, ms} (or {id, error}) out.

import { decodeFrame, fingerprint } from './decode.js';

self.onmessage = async (e) => {
  const { id, buffer, head } = e.data;
  const t0 = performance.now();
  try {
    const rgba = await decodeFrame(buffer, head);
    self.postMessage({ id, rgba, hash: fingerprint(rgba), ms: performance.now() - t0 }, [rgba.buffer]);
  } catch (err) {
    self.postMessage({ id, error: String(err) });
  }
};
