// The headset page: pairs with the board, sends the viewer and grip poses every XR frame, answers the
// board's clock pings, and draws the body the board returns. Uses the browser's own navigator.xr.
import { CLOCK_PING, CLOCK_PONG_SIZE, XR_BODY, XR_POSE_SIZE, decodeXrBody, describeShape, encodeClockPong,
         encodeXrPose, newBody, readBodyShape } from "./wire.js";
import { Mirror } from "./mirror.js";

const TOKEN_KEY = "edgepose.token";
const MAX_BUFFERED = 8 * 1024;      // bytes queued on the socket: beyond this a frame is skipped, not queued
const RECONNECT_MS = [100, 250, 500, 1000];
const $ = (id) => document.getElementById(id);

// Everything the page knows, also readable from the console (and by the tests) as window.edgepose.
const state = window.edgepose = {
  connected: false, paired: false, board: "", closeReason: "", reconnects: 0,
  sent: 0, skipped: 0, xrFrames: 0, bodies: 0, drawn: 0, lastSent: null, lastBody: null,
  rate: 0, latencyMs: null, samples: null, session: null, shape: null,
  roundTrips: new Float64Array(4096), roundTripCount: 0,     // every body's round trip (ms), a ring
};

let socket = null, code = null, retry = 0, retryTimer = null;
const poseBuffer = new DataView(new ArrayBuffer(XR_POSE_SIZE));
const pongBuffer = new DataView(new ArrayBuffer(CLOCK_PONG_SIZE));
const body = newBody();
let mirror = null, seq = 0, lastStatus = -Infinity;
const arrivals = new Float64Array(64), latencies = new Float64Array(64);
let arrivalCount = 0;

function show(text, error = false) {
  $("status").textContent = text;
  $("status").className = error ? "error" : "";
}

function askForCode(message) {
  $("pair").hidden = false;
  $("pair-error").textContent = message || "";
  $("code").focus();
}

$("pair").addEventListener("submit", (event) => {
  event.preventDefault();
  const typed = $("code").value.trim();
  if (!/^[0-9]{6}$/.test(typed)) { $("pair-error").textContent = "The code is 6 digits."; return; }
  code = typed;
  $("pair").hidden = true;
  connect();
});

function connect() {
  clearTimeout(retryTimer);
  const token = localStorage.getItem(TOKEN_KEY);
  if (!token && !code) { show("Not paired with this board yet."); askForCode(); return; }
  const url = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/socket`;
  const ws = socket = new WebSocket(url);
  ws.binaryType = "arraybuffer";
  // A connection still not open after 3 s (a Wi-Fi handover, a half-open TCP link) is given up and retried.
  const opening = setTimeout(() => { if (ws.readyState === WebSocket.CONNECTING) ws.close(); }, 3000);
  ws.onopen = () => {
    clearTimeout(opening);
    state.connected = true;
    ws.send(JSON.stringify(token ? { token } : { code }));
  };
  ws.onmessage = (event) => onMessage(ws, event.data);
  ws.onclose = (event) => onClose(ws, event);
}

function onMessage(ws, data) {
  if (typeof data === "string") {
    let hello;
    try { hello = JSON.parse(data); } catch { return; }      // not JSON: nothing the page can use
    if (hello.welcome) {
      localStorage.setItem(TOKEN_KEY, hello.token);
      code = null; retry = 0;
      state.paired = true; state.board = hello.board;
      show(`Paired with ${hello.board}. ${state.session ? "" : "Put the headset on and press Enter VR."}`);
      updateButtons();
    } else if (hello.body_shape !== undefined) {
      const shape = readBodyShape(hello);          // a malformed one is ignored: the body drawn stays
      if (shape) { state.shape = shape; if (mirror) mirror.setShape(shape.offsets); }
    }
    return;
  }
  const view = new DataView(data);
  const kind = view.byteLength ? view.getUint8(0) : -1;
  if (kind === CLOCK_PING && view.byteLength === 9) {
    encodeClockPong(pongBuffer, view.getFloat64(1, true), performance.now());
    ws.send(pongBuffer);
  } else if (kind === XR_BODY && decodeXrBody(view, body)) {
    const now = performance.now();
    arrivals[arrivalCount % 64] = now;
    latencies[arrivalCount % 64] = now - body.inputMs;
    state.roundTrips[state.roundTripCount++ % 4096] = now - body.inputMs;
    arrivalCount++;
    state.bodies++;
    state.samples = body.samples;
    state.lastBody = { seq: body.seq, inputMs: body.inputMs, root: Array.from(body.root) };
    if (mirror) mirror.setBody(body);
  }
}

function onClose(ws, event) {
  if (ws !== socket) return;
  state.connected = false; state.paired = false;
  state.closeReason = `${event.code} ${event.reason}`;
  updateButtons();
  if (event.code === 4001) { code = null; askForCode("Wrong code. Check the board's status line and try again."); show("Wrong pairing code.", true); return; }
  if (event.code === 4002) { localStorage.removeItem(TOKEN_KEY); code = null; askForCode("The board does not know this headset any more: pair again."); return; }
  if (event.code === 4003) { code = null; askForCode(event.reason); show("Pairing is locked for a minute.", true); return; }
  if (event.code === 4009) show("The board is busy with another headset; trying again...", true);
  else show(`Connection lost (${event.reason || event.code}); reconnecting...`, true);
  state.reconnects++;
  retryTimer = setTimeout(connect, RECONNECT_MS[Math.min(retry++, RECONNECT_MS.length - 1)]);
}

// ---- XR -------------------------------------------------------------------------------------------

async function updateButtons() {
  const xr = navigator.xr;
  const vr = xr && await xr.isSessionSupported("immersive-vr").catch(() => false);
  const ar = xr && await xr.isSessionSupported("immersive-ar").catch(() => false);
  $("enter-vr").disabled = !vr || !state.paired || !!state.session;
  $("enter-ar").disabled = !ar || !state.paired || !!state.session;
  if (!xr) $("details").textContent = window.isSecureContext
    ? "This browser has no WebXR: open the page in the headset's browser."
    : "WebXR needs a secure page: open https://<board>:8443 (or http://localhost over adb reverse).";
}

async function enter(mode) {
  const session = await navigator.xr.requestSession(mode, { requiredFeatures: ["local-floor"] });
  const canvas = document.createElement("canvas");
  const gl = canvas.getContext("webgl2", { xrCompatible: true, antialias: true });
  const layer = new XRWebGLLayer(session, gl);
  session.updateRenderState({ baseLayer: layer });
  const space = await session.requestReferenceSpace("local-floor");
  mirror = new Mirror(gl);
  if (state.shape) mirror.setShape(state.shape.offsets);
  mirror.passthrough = session.environmentBlendMode !== undefined && session.environmentBlendMode !== "opaque";
  state.session = mode;
  updateButtons();
  session.addEventListener("end", () => { state.session = null; mirror = null; updateButtons(); });
  const onFrame = (time, frame) => {
    session.requestAnimationFrame(onFrame);
    state.xrFrames++;
    const pose = frame.getViewerPose(space);
    if (!pose) return;
    let left = null, right = null;
    for (const source of session.inputSources) {
      if (!source.gripSpace) continue;
      const grip = frame.getPose(source.gripSpace, space);
      if (!grip) continue;
      if (source.handedness === "left") left = grip.transform;
      else if (source.handedness === "right") right = grip.transform;
    }
    send(time, pose.transform, left, right);
    if (mirror.hasBody) mirror.follow(pose.transform);
    if (time - lastStatus > 250) { lastStatus = time; mirror.setStatus(statusLines()); }
    if (mirror.draw(pose, session.renderState.baseLayer)) state.drawn++;
  };
  session.requestAnimationFrame(onFrame);
}

function send(time, head, left, right) {
  const ws = socket;
  if (!ws || ws.readyState !== WebSocket.OPEN || !state.paired) return;
  if (ws.bufferedAmount > MAX_BUFFERED) { state.skipped++; return; }     // the link is behind: stay current
  encodeXrPose(poseBuffer, seq, time, head, left, right);
  ws.send(poseBuffer);
  state.lastSent = { seq, time };
  seq = (seq + 1) & 0xffff;
  state.sent++;
}

function statusLines() {
  const n = Math.min(arrivalCount, 64);
  const newest = arrivals[(arrivalCount - 1) % 64], oldest = arrivals[(arrivalCount - n) % 64];
  state.rate = n > 1 && newest > oldest ? (n - 1) * 1000 / (newest - oldest) : 0;
  if (performance.now() - newest > 1000) state.rate = 0;
  const recent = Array.from(latencies.subarray(0, n)).sort((a, b) => a - b);
  state.latencyMs = n ? recent[n >> 1] : null;
  const link = state.paired ? "connected" : state.connected ? "pairing..." : "reconnecting...";
  return [`${link}  ${state.rate.toFixed(0)}/s`,
          `lag ${state.latencyMs === null ? "-" : state.latencyMs.toFixed(0)} ms   N=${state.samples ?? "-"}`,
          state.shape ? `body ${describeShape(state.shape)}` : ""];
}

$("enter-vr").addEventListener("click", () => enter("immersive-vr").catch((e) => show(`Enter VR failed: ${e.message}`, true)));
$("enter-ar").addEventListener("click", () => enter("immersive-ar").catch((e) => show(`Enter AR failed: ${e.message}`, true)));
updateButtons();
connect();
