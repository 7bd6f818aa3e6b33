// The WebXR headset link's messages, page side (protocol.md section 9; the board's decoder is
// firmware_bridge/wire/webxr.py). Little-endian, one type byte first. Encoders write into buffers
// the caller reuses, so an XR frame allocates nothing.
export const XR_POSE = 0x02, XR_BODY = 0x03, CLOCK_PING = 0x20, CLOCK_PONG = 0x21;
export const XR_POSE_SIZE = 74, XR_BODY_SIZE = 192, CLOCK_PONG_SIZE = 17;
const Q14 = 16384;

// WebXR's viewer and grip poses look down -Z; edgepose's body faces +Z in its rest pose (protocol.md
// section 2). Turning each orientation half a turn about its own Y: (w,x,y,z) * (0,0,1,0) = (-y,-z,w,x).
function writeRotation(view, at, o) {
  const n = Math.hypot(o.x, o.y, o.z, o.w) || 1;
  const q = [-o.y / n, -o.z / n, o.w / n, o.x / n];
  for (let k = 0; k < 4; k++) view.setInt16(at + 2 * k, Math.max(-32768, Math.min(32767, Math.round(q[k] * Q14))), true);
}

function writePosition(view, at, p) {
  view.setFloat32(at, p.x, true); view.setFloat32(at + 4, p.y, true); view.setFloat32(at + 8, p.z, true);
}

// One XR_POSE: seq, the XR frame's time (ms, performance.now()'s clock), the viewer's transform and the
// left and right grip transforms (null: that controller is not tracked).
export function encodeXrPose(view, seq, timeMs, head, left, right) {
  view.setUint8(0, XR_POSE); view.setUint8(1, 0); view.setUint16(2, seq & 0xffff, true);
  view.setFloat64(4, timeMs, true);
  writePosition(view, 12, head.position); writeRotation(view, 24, head.orientation);
  [left, right].forEach((grip, k) => {
    const at = 32 + 21 * k;
    view.setUint8(at, grip ? 1 : 0);
    if (grip) { writePosition(view, at + 1, grip.position); writeRotation(view, at + 13, grip.orientation); }
    else {
      for (let b = 1; b < 21; b++) view.setUint8(at + b, 0);
      view.setInt16(at + 13, Q14, true);          // untracked: zeros and the identity
    }
  });
}

export function encodeClockPong(view, boardMs, pageMs) {
  view.setUint8(0, CLOCK_PONG); view.setFloat64(1, boardMs, true); view.setFloat64(9, pageMs, true);
}

// An XR_BODY into `body` (reused): {seq, inputMs, root[3], rotations[84] (w,x,y,z per joint), contacts[2],
// samples, ssiFlags, trackersLost}. False if the message is not a whole XR_BODY.
export function decodeXrBody(view, body) {
  if (view.byteLength !== XR_BODY_SIZE || view.getUint8(0) !== XR_BODY) return false;
  body.seq = view.getUint16(2, true);
  body.inputMs = view.getFloat64(4, true);
  for (let k = 0; k < 3; k++) body.root[k] = view.getInt16(12 + 2 * k, true) / 1000;
  for (let j = 0; j < 21; j++) {
    let n = 0;
    for (let k = 0; k < 4; k++) { const v = view.getInt16(18 + 8 * j + 2 * k, true) / Q14; body.rotations[4 * j + k] = v; n += v * v; }
    n = Math.sqrt(n) || 1;
    for (let k = 0; k < 4; k++) body.rotations[4 * j + k] /= n;
  }
  body.contacts[0] = view.getUint8(186) / 255; body.contacts[1] = view.getUint8(187) / 255;
  body.samples = view.getUint8(188); body.ssiFlags = view.getUint8(189); body.trackersLost = view.getUint16(190, true);
  return true;
}

export function newBody() {
  return { seq: 0, inputMs: 0, root: new Float64Array(3), rotations: new Float64Array(84), contacts: new Float64Array(2),
           samples: 0, ssiFlags: 0, trackersLost: 0 };
}

// A BODY_SHAPE text message, already parsed from JSON (protocol.md section 9.2): the rest offsets of the
// user's body the XR_BODYs are posed on, metres at the user's size. The shape, or null when it is not
// one (21 offsets of 3 finite numbers within 1 m, a stature of 0.5-2.5 m): the page then keeps the body
// it had.
export function readBodyShape(message) {
  if (!message || message.body_shape !== 1 || !Array.isArray(message.offsets) || message.offsets.length !== 21) return null;
  const offsets = [];
  for (const o of message.offsets) {
    if (!Array.isArray(o) || o.length !== 3 || !o.every((v) => typeof v === "number" && Number.isFinite(v) && Math.abs(v) <= 1)) return null;
    offsets.push([o[0], o[1], o[2]]);
  }
  const stature = message.stature_m, legs = message.legs ?? 1, arms = message.arms ?? 1;
  if (typeof stature !== "number" || !(stature >= 0.5 && stature <= 2.5)) return null;
  if (![legs, arms].every((v) => typeof v === "number" && v >= 0.5 && v <= 1.5)) return null;
  return { offsets, stature, legs, arms };
}

// The shape in a few words for the panel: the height, and the limbs where they are not the average's.
export function describeShape(shape) {
  if (!shape) return "";
  const limb = (name, v) => (Math.abs(v - 1) >= 0.005 ? ` ${name} ${v.toFixed(2)}x` : "");
  return `${shape.stature.toFixed(2)} m${limb("legs", shape.legs)}${limb("arms", shape.arms)}`;
}
