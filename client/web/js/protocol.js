// The streaming protocol (docs/PROTOCOL.md), as the page speaks it.

export const PROTOCOL_VERSION = 1;
export const HEADER_SIZE = 48;
export const FLAG_COMPLETE = 1, FLAG_FINAL = 2, FLAG_MOVING = 4, FLAG_SCREENSHOT = 8;

export function parseFrame(buffer) {
  const view = new DataView(buffer);
  const magic = String.fromCharCode(...new Uint8Array(buffer, 0, 4));
  if (magic !== "VRF1") throw new Error(`not a vastray frame (${magic})`);
  const size = view.getUint16(4, true);
  const flags = view.getUint8(7);
  return {
    format: view.getUint8(6) === 1 ? "image/png" : "image/jpeg",
    flags,
    complete: (flags & FLAG_COMPLETE) !== 0,
    final: (flags & FLAG_FINAL) !== 0,
    moving: (flags & FLAG_MOVING) !== 0,
    screenshot: (flags & FLAG_SCREENSHOT) !== 0,
    frame: view.getUint32(8, true),
    cameraSeq: view.getUint32(12, true),
    width: view.getUint16(16, true),
    height: view.getUint16(18, true),
    pass: view.getUint16(20, true),
    renderMs: view.getFloat32(24, true),
    encodeMs: view.getFloat32(28, true),
    pixelsOfError: view.getFloat32(32, true),
    scale: view.getFloat32(36, true),
    sentAt: view.getFloat64(40, true),
    image: new Blob([new Uint8Array(buffer, size)], { type: view.getUint8(6) === 1 ? "image/png" : "image/jpeg" }),
  };
}
