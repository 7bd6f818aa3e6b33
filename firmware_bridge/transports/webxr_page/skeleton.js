// The body the board sends (protocol.md section 5): joint order, parents and rest offsets of the
// canonical 1.75 m skeleton (edge.skeleton; tests/test_webxr_page.py holds these equal to it).
export const JOINT_NAMES = ["pelvis", "spine", "chest", "neck", "head", "l_collar", "l_shoulder", "l_elbow",
  "l_wrist", "r_collar", "r_shoulder", "r_elbow", "r_wrist", "l_hip", "l_knee", "l_ankle", "l_toe", "r_hip",
  "r_knee", "r_ankle", "r_toe"];
export const PARENTS = [-1, 0, 1, 2, 3, 2, 5, 6, 7, 2, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19];
export const OFFSETS = [[0, 0, 0], [0, 0.11, 0], [0, 0.2, 0], [0, 0.22, 0], [0, 0.1, 0], [0.03, 0.17, 0],
  [0.14, 0, 0], [0.28, 0, 0], [0.25, 0, 0], [-0.03, 0.17, 0], [-0.14, 0, 0], [-0.28, 0, 0], [-0.25, 0, 0],
  [0.09, -0.06, 0], [0, -0.43, 0], [0, -0.42, 0], [0, -0.07, 0.13], [-0.09, -0.06, 0], [0, -0.43, 0],
  [0, -0.42, 0], [0, -0.07, 0.13]];
export const NUM_JOINTS = JOINT_NAMES.length;

// q = a * b for quaternions (w, x, y, z) stored at offsets in Float64Arrays (no allocation).
function mulInto(out, o, a, ia, b, ib) {
  const aw = a[ia], ax = a[ia + 1], ay = a[ia + 2], az = a[ia + 3];
  const bw = b[ib], bx = b[ib + 1], by = b[ib + 2], bz = b[ib + 3];
  out[o] = aw * bw - ax * bx - ay * by - az * bz;
  out[o + 1] = aw * bx + ax * bw + ay * bz - az * by;
  out[o + 2] = aw * by - ax * bz + ay * bw + az * bx;
  out[o + 3] = aw * bz + ax * by - ay * bx + az * bw;
}

// v rotated by the unit quaternion q[iq..iq+3], added to base[ib..], written to out[o..].
function rotateAddInto(out, o, q, iq, v, base, ib) {
  const w = q[iq], x = q[iq + 1], y = q[iq + 2], z = q[iq + 3];
  const tx = 2 * (y * v[2] - z * v[1]), ty = 2 * (z * v[0] - x * v[2]), tz = 2 * (x * v[1] - y * v[0]);
  out[o] = base[ib] + v[0] + w * tx + (y * tz - z * ty);
  out[o + 1] = base[ib + 1] + v[1] + w * ty + (z * tx - x * tz);
  out[o + 2] = base[ib + 2] + v[2] + w * tz + (x * ty - y * tx);
}

// Forward kinematics: local rotations [21*4] (w, x, y, z) and the root position [3] -> world joint
// positions [21*3], using `worldRot` [21*4] as scratch, on the bones `offsets` (the user's body the board
// sent in BODY_SHAPE; the canonical one until then). Parents come before their children.
export function forwardKinematics(local, root, positions, worldRot, offsets = OFFSETS) {
  for (let j = 0; j < NUM_JOINTS; j++) {
    const p = PARENTS[j];
    if (p < 0) {
      for (let k = 0; k < 4; k++) worldRot[k] = local[k];
      positions[0] = root[0]; positions[1] = root[1]; positions[2] = root[2];
    } else {
      mulInto(worldRot, 4 * j, worldRot, 4 * p, local, 4 * j);
      rotateAddInto(positions, 3 * j, worldRot, 4 * p, offsets[j], positions, 3 * p);
    }
  }
}
