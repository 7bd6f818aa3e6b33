// Draws the body the board returns as a mirror image in front of the user, and a small status panel
// under it, into each XR view. WebGL2, flat colours, buffers made once: a frame only refills them.
import { forwardKinematics, NUM_JOINTS, OFFSETS, PARENTS } from "./skeleton.js";

const BONE_WIDTH = 0.035;          // metres
const MIRROR_DISTANCE = 1.0;       // the mirror plane this far in front of the head: the body shows at twice that
const LEFT = [0.15, 0.55, 1.0], RIGHT = [1.0, 0.55, 0.1], CENTRE = [0.95, 0.95, 0.95];
const PANEL_PX = [512, 192];       // the status panel's texture: three lines
const CORNER_END = [0, 0, 1, 0, 1, 1], CORNER_SIDE = [-1, 1, 1, -1, 1, -1];
const BONES = [];
for (let j = 1; j < NUM_JOINTS; j++) BONES.push(j);

function compile(gl, vertex, fragment) {
  const program = gl.createProgram();
  for (const [kind, source] of [[gl.VERTEX_SHADER, vertex], [gl.FRAGMENT_SHADER, fragment]]) {
    const shader = gl.createShader(kind);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(shader));
    gl.attachShader(program, shader);
  }
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
  return program;
}

const BODY_VS = `#version 300 es
in vec3 position; in vec3 colour; uniform mat4 projection; uniform mat4 view; out vec3 vColour;
void main() { vColour = colour; gl_Position = projection * view * vec4(position, 1.0); }`;
const BODY_FS = `#version 300 es
precision mediump float; in vec3 vColour; out vec4 outColour; void main() { outColour = vec4(vColour, 1.0); }`;
const PANEL_VS = `#version 300 es
in vec3 position; in vec2 uv; uniform mat4 projection; uniform mat4 view; out vec2 vUv;
void main() { vUv = uv; gl_Position = projection * view * vec4(position, 1.0); }`;
const PANEL_FS = `#version 300 es
precision mediump float; in vec2 vUv; uniform sampler2D text; out vec4 outColour;
void main() { outColour = texture(text, vUv); }`;

export class Mirror {
  constructor(gl) {
    this.gl = gl;
    this.body = compile(gl, BODY_VS, BODY_FS);
    this.panel = compile(gl, PANEL_VS, PANEL_FS);
    this.positions = new Float64Array(3 * NUM_JOINTS);
    this.worldRot = new Float64Array(4 * NUM_JOINTS);
    this.mirrored = new Float64Array(3 * NUM_JOINTS);
    this.vertices = new Float32Array(BONES.length * 6 * 6);       // 2 triangles per bone, xyz + rgb
    this.vbo = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.vbo);
    gl.bufferData(gl.ARRAY_BUFFER, this.vertices.byteLength, gl.DYNAMIC_DRAW);
    this.panelVertices = new Float32Array(6 * 5);
    this.panelVbo = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.panelVbo);
    gl.bufferData(gl.ARRAY_BUFFER, this.panelVertices.byteLength, gl.DYNAMIC_DRAW);
    this.canvas = document.createElement("canvas");
    [this.canvas.width, this.canvas.height] = PANEL_PX;
    this.text = this.canvas.getContext("2d");
    this.texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    this.plane = null;             // {point, normal}: set from the head when the first body arrives
    this.hasBody = false;
    this.offsets = OFFSETS;        // the canonical body until the board says whose it is
    this.passthrough = false;
    this.statusLines = ["", "", ""];
    this.setStatus(["connecting...", "", ""]);
  }

  // Keep the mirror in front: placed when the first body arrives, and again when the user has walked up
  // to it (or past it), away from it, or turned more than ~50 degrees from it. Between, it stays put,
  // as a real mirror does, so the body can be seen walking towards and away from it.
  follow(head) {
    if (this.plane) {
      const o = head.orientation, p = head.position, { point, normal } = this.plane;
      const fx = -2 * (o.x * o.z + o.w * o.y), fz = -(1 - 2 * (o.x * o.x + o.y * o.y));
      const facing = (fx * normal[0] + fz * normal[2]) / (Math.hypot(fx, fz) || 1);
      const ahead = (point[0] - p.x) * normal[0] + (point[2] - p.z) * normal[2];
      if (ahead > 0.4 && ahead < 2.5 && facing > 0.64) return;
    }
    this.placeInFront(head);
  }

  // Place the mirror MIRROR_DISTANCE in front of where the head looks now (level, whatever the pitch).
  placeInFront(head) {
    const o = head.orientation, p = head.position;
    // -Z of the head's rotation, projected on the floor
    let fx = -2 * (o.x * o.z + o.w * o.y), fz = -(1 - 2 * (o.x * o.x + o.y * o.y));
    const n = Math.hypot(fx, fz) || 1;
    fx /= n; fz /= n;
    this.plane = { point: [p.x + MIRROR_DISTANCE * fx, p.y, p.z + MIRROR_DISTANCE * fz], normal: [fx, 0, fz] };
  }

  // The user's body (BODY_SHAPE's offsets): every body after this is drawn on its bones.
  setShape(offsets) {
    this.offsets = offsets;
  }

  setBody(body) {
    forwardKinematics(body.rotations, body.root, this.positions, this.worldRot, this.offsets);
    this.hasBody = true;
  }

  // Three lines: the link, the lag and N, the body drawn (BODY_SHAPE's height and limbs).
  setStatus(lines) {
    if (lines.every((line, k) => line === this.statusLines[k])) return;
    this.statusLines = lines;
    const c = this.text;
    c.fillStyle = "rgba(20, 24, 30, 0.85)"; c.fillRect(0, 0, PANEL_PX[0], PANEL_PX[1]);
    c.fillStyle = "#f2f2f2"; c.font = "bold 40px sans-serif"; c.fillText(lines[0], 16, 52);
    c.font = "32px sans-serif"; c.fillStyle = "#b8c4d0"; c.fillText(lines[1], 16, 104);
    c.fillText(lines[2] || "", 16, 160);
    const gl = this.gl;
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA, gl.RGBA, gl.UNSIGNED_BYTE, this.canvas);
  }

  // Reflect the body in the mirror plane and build each bone as a flat ribbon facing the eye.
  _buildBones(eye) {
    const { point, normal } = this.plane, src = this.positions, dst = this.mirrored;
    for (let j = 0; j < NUM_JOINTS; j++) {
      const d = (src[3 * j] - point[0]) * normal[0] + (src[3 * j + 2] - point[2]) * normal[2];
      dst[3 * j] = src[3 * j] - 2 * d * normal[0];
      dst[3 * j + 1] = src[3 * j + 1];
      dst[3 * j + 2] = src[3 * j + 2] - 2 * d * normal[2];
    }
    const v = this.vertices;
    let at = 0;
    for (const j of BONES) {
      const p = PARENTS[j];
      const ax = dst[3 * p], ay = dst[3 * p + 1], az = dst[3 * p + 2];
      const bx = dst[3 * j], by = dst[3 * j + 1], bz = dst[3 * j + 2];
      const dx = bx - ax, dy = by - ay, dz = bz - az;
      const ex = eye.x - ax, ey = eye.y - ay, ez = eye.z - az;
      let sx = dy * ez - dz * ey, sy = dz * ex - dx * ez, sz = dx * ey - dy * ex;
      const s = (Math.hypot(sx, sy, sz) || 1) / (BONE_WIDTH / 2);
      sx /= s; sy /= s; sz /= s;
      const colour = j >= 13 ? (j < 17 ? LEFT : RIGHT) : (j >= 5 && j < 9 ? LEFT : j >= 9 ? RIGHT : CENTRE);
      // two triangles: a-, a+, b+ and a-, b+, b-
      for (let k = 0; k < 6; k++) {
        const end = CORNER_END[k], side = CORNER_SIDE[k];
        v[at] = (end ? bx : ax) + side * sx; v[at + 1] = (end ? by : ay) + side * sy; v[at + 2] = (end ? bz : az) + side * sz;
        v[at + 3] = colour[0]; v[at + 4] = colour[1]; v[at + 5] = colour[2];
        at += 6;
      }
    }
  }

  _buildPanel() {
    const { point, normal } = this.plane;
    const rx = -normal[2], rz = normal[0];          // to the user's right when facing the mirror
    // closer than the mirror, low and to the right, so it is easy to read and never covers the body
    const w = 0.2, h = w * PANEL_PX[1] / PANEL_PX[0], y = point[1] - 0.35, side = 0.4, near = 0.4;
    const cx = point[0] - near * normal[0] + side * rx, cz = point[2] - near * normal[2] + side * rz;
    const c = [[cx - w * rx, y + h, cz - w * rz, 0, 0], [cx - w * rx, y - h, cz - w * rz, 0, 1],
               [cx + w * rx, y - h, cz + w * rz, 1, 1], [cx - w * rx, y + h, cz - w * rz, 0, 0],
               [cx + w * rx, y - h, cz + w * rz, 1, 1], [cx + w * rx, y + h, cz + w * rz, 1, 0]];
    c.forEach((row, k) => this.panelVertices.set(row, 5 * k));
  }

  // Draw into every view of an XR frame; true when a body was drawn.
  draw(pose, layer) {
    const gl = this.gl;
    gl.bindFramebuffer(gl.FRAMEBUFFER, layer.framebuffer);
    if (this.passthrough) gl.clearColor(0, 0, 0, 0);      // AR: the room shows through
    else gl.clearColor(0.04, 0.05, 0.07, 1.0);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    if (!this.plane) return false;
    gl.enable(gl.DEPTH_TEST);
    this._buildPanel();
    let drew = false;
    for (const view of pose.views) {
      const vp = layer.getViewport(view);
      if (!vp || vp.width === 0) continue;
      gl.viewport(vp.x, vp.y, vp.width, vp.height);
      const eye = view.transform.position;
      if (this.hasBody) {
        this._buildBones(eye);
        this._drawArrays(this.body, this.vbo, this.vertices, view, [["position", 3], ["colour", 3]], 6, BONES.length * 6);
        drew = true;
      }
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.texture);
      this._drawArrays(this.panel, this.panelVbo, this.panelVertices, view, [["position", 3], ["uv", 2]], 5, 6);
    }
    return drew;
  }

  _drawArrays(program, vbo, data, view, attributes, stride, count) {
    const gl = this.gl;
    gl.useProgram(program);
    gl.bindBuffer(gl.ARRAY_BUFFER, vbo);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, data);
    let offset = 0;
    for (const [name, size] of attributes) {
      const at = gl.getAttribLocation(program, name);
      gl.enableVertexAttribArray(at);
      gl.vertexAttribPointer(at, size, gl.FLOAT, false, stride * 4, offset * 4);
      offset += size;
    }
    gl.uniformMatrix4fv(gl.getUniformLocation(program, "projection"), false, view.projectionMatrix);
    gl.uniformMatrix4fv(gl.getUniformLocation(program, "view"), false, view.transform.inverse.matrix);
    gl.drawArrays(gl.TRIANGLES, 0, count);
  }
}
