"""Record the output stream as a BVH file (Blender, MotionBuilder, motion.bvh and other readers).

The file is the canonical skeleton as edgepose sees it: Y-up, the character facing +Z with its left
at +X, offsets and root positions in centimetres (Blender's importer takes a scale: use 0.01 for
metres), joint names from edge.skeleton, End Sites on the leaf joints so they show as bones.

Channels: the root has "Xposition Yposition Zposition Zrotation Xrotation Yrotation", every other
joint "Zrotation Xrotation Yrotation". BVH channels are intrinsic, in the order listed, so a joint's
local rotation is R = Rz(z) @ Rx(x) @ Ry(y), angles in degrees; `zxy_euler_degrees` inverts that.

Streaming: the header goes out when the writer opens, one MOTION line per send, and the frame
count (written as a fixed-width placeholder) is filled in by flush() and close().

    with BvhWriter("take.bvh", fps=60) as bvh:
        for pose in poses:
            bvh.send(pose)
"""
import numpy as np

from edge.skeleton import JOINT_NAMES, NUM_JOINTS, OFFSETS, PARENTS
from firmware_bridge.outputs import PoseSink

CM_PER_M = 100.0
ROOT_CHANNELS = "Xposition Yposition Zposition Zrotation Xrotation Yrotation"
JOINT_CHANNELS = "Zrotation Xrotation Yrotation"
# Leaf joints carry no bone to show their length; these End Sites give them one (metres, rest pose).
END_SITES = {
    "head": (0.0, 0.15, 0.0),       # base of the skull -> top of the head
    "l_wrist": (0.10, 0.0, 0.0),    # wrist -> fingertips, roughly
    "r_wrist": (-0.10, 0.0, 0.0),
    "l_toe": (0.0, 0.0, 0.05),      # ball of the foot -> tip of the toes
    "r_toe": (0.0, 0.0, 0.05),
}
FRAME_COUNT_WIDTH = 10              # room for 10 digits: 5 years at 60 Hz
VALUE_FORMAT = "%.6f"
GIMBAL_EPS = 1e-9


def zxy_euler_degrees(m):
    """Rotation matrices [...,3,3] -> BVH angles [...,3] (z, x, y) in degrees with R = Rz Rx Ry.

    With c = cos(x): R[2,1] = sin(x), R[2,0] = -sin(y) c, R[2,2] = cos(y) c, R[0,1] = -sin(z) c,
    R[1,1] = cos(z) c. At x = +-90 degrees (c = 0) only z + y or z - y is defined: we put it all in z.
    """
    cos_x = np.hypot(m[..., 2, 0], m[..., 2, 2])
    x = np.arctan2(m[..., 2, 1], cos_x)
    gimbal = cos_x < GIMBAL_EPS
    y = np.where(gimbal, 0.0, np.arctan2(-m[..., 2, 0], m[..., 2, 2]))
    z = np.where(gimbal, np.arctan2(m[..., 1, 0], m[..., 0, 0]), np.arctan2(-m[..., 0, 1], m[..., 1, 1]))
    return np.degrees(np.stack([z, x, y], axis=-1))


def children_of(parents=PARENTS):
    """Each joint's children, in joint-index order."""
    children = [[] for _ in parents]
    for joint, parent in enumerate(parents):
        if parent >= 0:
            children[parent].append(joint)
    return children


def depth_first_order(parents=PARENTS):
    """Joint indices in the order a BVH hierarchy lists them (and so the order of MOTION channels)."""
    children = children_of(parents)
    order, stack = [], [int(np.flatnonzero(np.asarray(parents) < 0)[0])]
    while stack:
        joint = stack.pop()
        order.append(joint)
        stack.extend(reversed(children[joint]))
    return np.array(order)


def format_offset(offset_m):
    return "OFFSET " + " ".join(VALUE_FORMAT % (v * CM_PER_M) for v in offset_m)


def hierarchy_text(names=JOINT_NAMES, parents=PARENTS, offsets=OFFSETS):
    """The HIERARCHY section, offsets in centimetres."""
    children = children_of(parents)
    lines = ["HIERARCHY"]

    def joint(j, depth):
        pad = "\t" * depth
        lines.append(f"{pad}{'ROOT' if parents[j] < 0 else 'JOINT'} {names[j]}")
        lines.append(pad + "{")
        lines.append(f"{pad}\t{format_offset(offsets[j])}")
        channels = ROOT_CHANNELS if parents[j] < 0 else JOINT_CHANNELS
        lines.append(f"{pad}\tCHANNELS {len(channels.split())} {channels}")
        for c in children[j]:
            joint(c, depth + 1)
        if not children[j]:
            end = END_SITES.get(names[j], (0.0, 0.0, 0.0))
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\t{format_offset(end)}", f"{pad}\t}}"])
        lines.append(pad + "}")

    joint(depth_first_order(parents)[0], 0)
    return "\n".join(lines) + "\n"


def frame_count_line(frames):
    """'Frames: N' padded to a fixed width, so close() can overwrite it in place."""
    if frames >= 10 ** FRAME_COUNT_WIDTH:
        raise ValueError(f"{frames} frames do not fit the BVH header's {FRAME_COUNT_WIDTH} digits")
    return f"Frames: {frames:<{FRAME_COUNT_WIDTH}d}\n"


def frame_values(local_rot, root_pos, order, out=None):
    """One MOTION row [3 + 3J]: root position (cm), then (z, x, y) degrees per joint in `order`."""
    out = np.empty(3 + 3 * len(order)) if out is None else out
    out[:3] = root_pos * CM_PER_M
    out[3:] = zxy_euler_degrees(local_rot[order]).ravel()
    return out


class BvhWriter(PoseSink):
    """Streams Poses into a BVH file; the frame count is right once flush() or close() has run."""

    def __init__(self, path, fps=60.0, scale=1.0, offsets=None):
        """scale sizes the body: the calibrated user's (1 / height_scale) instead of the canonical one;
        offsets: the skeleton in the canonical body's units (the user's legs, edge.proportions; None:
        the canonical skeleton)."""
        if not fps > 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.path = str(path)
        self.fps = float(fps)
        self.frames = 0
        self._order = depth_first_order(PARENTS)
        self._row = np.empty(3 + 3 * NUM_JOINTS)
        self._row_format = " ".join([VALUE_FORMAT] * len(self._row)) + "\n"
        self._file = open(self.path, "wb")
        self.scale = float(scale)
        skeleton = OFFSETS if offsets is None else np.asarray(offsets, float)
        self._file.write((hierarchy_text(offsets=skeleton * self.scale) + "MOTION\n").encode("ascii"))
        self._count_at = self._file.tell()
        self._file.write(frame_count_line(0).encode("ascii"))
        self._file.write(f"Frame Time: {1.0 / self.fps:.8f}\n".encode("ascii"))

    def send(self, pose):
        """Append one Pose (local rotations and the root position; world positions follow by FK)."""
        frame_values(pose.rotations, pose.positions[0] * self.scale, self._order, out=self._row)
        self._file.write((self._row_format % tuple(self._row)).encode("ascii"))
        self.frames += 1

    def flush(self):
        """Write the frame count so far into the header and flush: the file is valid up to here."""
        end = self._file.tell()
        self._file.seek(self._count_at)
        self._file.write(frame_count_line(self.frames).encode("ascii"))
        self._file.seek(end)
        self._file.flush()

    def close(self):
        """Fill in the frame count and close. A take with no frames says 'Frames: 0', which some
        readers (motion.bvh among them) refuse."""
        if self._file.closed:
            return
        self.flush()
        self._file.close()
