// Frame images to premultiplied RGBA pixels. Used in a worker (decoder.js) so that decoding never
// waits behind the page's drawing, and on the page itself where workers are unavailable. No
// imports of three.js here: workers do not see the page's import map.

import { FORMAT_PNG, FORMAT_RAW, HEADER_BYTES } from './stream.js';

const BITMAP = { premultiplyAlpha: 'none', colorSpaceConversion: 'none' };
let scratch = null;

function pixelsOf(bitmap) {
  const w = bitmap.width, h = bitmap.height;
  if (!scratch || scratch.canvas.width !== w || scratch.canvas.height !== h) {
    const c = typeof OffscreenCanvas !== 'undefined'
      ? new OffscreenCanvas(w, h) : Object.assign(document.createElement('canvas'), { width: w, height: h });
    scratch = c.getContext('2d', { willReadFrequently: true, colorSpace: 'srgb' });
  }
  scratch.globalCompositeOperation = 'copy';
  scratch.drawImage(bitmap, 0, 0);
  bitmap.close?.();
  return scratch.getImageData(0, 0, w, h).data;
}

/** The premultiplied RGBA (Uint8Array, rows top to bottom) of a frame message (its straight
 *  colour and alpha: JPEG + greyscale PNG, or one RGBA PNG). Premultiplied so that texture
 *  filtering never mixes the colour of transparent pixels into the edges. */
export async function decodeFrame(buffer, head) {
  if (head.format === FORMAT_RAW) return rawPixels(buffer, head);
  const colour = new Blob([new Uint8Array(buffer, HEADER_BYTES, head.colourBytes)],
                          { type: head.format === FORMAT_PNG ? 'image/png' : 'image/jpeg' });
  const pending = [createImageBitmap(colour, BITMAP)];
  if (head.format !== FORMAT_PNG) {
    const alpha = new Blob([new Uint8Array(buffer, HEADER_BYTES + head.colourBytes, head.alphaBytes)],
                           { type: 'image/png' });
    pending.push(createImageBitmap(alpha, BITMAP));
  }
  const [cb, ab] = await Promise.all(pending);
  const rgba = new Uint8Array(pixelsOf(cb));
  if (ab) {
    const a = pixelsOf(ab);                 // grey: R = G = B = alpha
    for (let i = 3; i < rgba.length; i += 4) rgba[i] = a[i - 3];
  }
  return premultiply(rgba);
}

/** The premultiplied RGBA of a raw frame (format 2): a copy of its straight bytes, premultiplied.
 *  No image decoder involved: a fraction of a millisecond at 256 px, so the page does it itself. */
export function rawPixels(buffer, head) {
  if (head.colourBytes !== 4 * head.width * head.height) throw new Error('a raw frame of the wrong length');
  return premultiply(new Uint8Array(buffer.slice(HEADER_BYTES, HEADER_BYTES + head.colourBytes)));
}

function premultiply(rgba) {
  for (let i = 0; i < rgba.length; i += 4) {
    const a = rgba[i + 3];
    if (a === 255) continue;
    rgba[i] = (rgba[i] * a + 127) / 255;
    rgba[i + 1] = (rgba[i + 1] * a + 127) / 255;
    rgba[i + 2] = (rgba[i + 2] * a + 127) / 255;
  }
  return rgba;
}

/** A cheap fingerprint of a frame's pixels (tests compare it between frames). */
export function fingerprint(rgba) {
  let h = 2166136261 >>> 0;
  const stride = Math.max(4, (Math.floor(rgba.length / 4096) >> 2) << 2);
  for (let i = 0; i < rgba.length; i += stride) {
    h ^= rgba[i] | (rgba[i + 1] << 8) | (rgba[i + 2] << 16) | (rgba[i + 3] << 24);
    h = Math.imul(h, 16777619) >>> 0;
  }
  return h.toString(16);
}
