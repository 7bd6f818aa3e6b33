"""VMC protocol sender: the pose as a VRM humanoid over OSC/UDP (protocol.vmc.info).

Per frame, in this order:
    /VMC/Ext/Root/Pos  "root"  p.x p.y p.z  q.x q.y q.z q.w
    /VMC/Ext/Bone/Pos  <Unity HumanBodyBones name>  p.x p.y p.z  q.x q.y q.z q.w   (21 bones)
    /VMC/Ext/OK        1                                 (model loaded)
    /VMC/Ext/T         <seconds>

Values are Unity transforms (left-handed, Y-up, metres; see firmware_bridge.outputs for the mirror):
- root: the tracking-space origin, identity rotation. The body's world placement is carried by the
  Hips, as Unity's hierarchy has it: Hips' local transform relative to the root is the pelvis's
  world position and rotation.
- every other bone: local position = the skeleton offset from its parent (constant, our 1.75 m
  skeleton), local rotation = the pose's local rotation. Our rest local rotations are the identity
  in a T-pose facing +Z, which is VRM's normalized-bone convention, so they apply as they are.

`mode` chooses the datagrams (`[output] vmc_mode`):
- "split" (the default): OSC bundles of at most 1,472 bytes each, one Ethernet frame's UDP payload, in
  frame order (two per frame): nothing is IP-fragmented on a LAN, where losing one fragment loses both;
- "bundle": the whole frame in one bundle (about 1.75 kB): one datagram, applied at once by the
  receiver, fine on loopback, fragmented over Ethernet;
- "messages": each message its own datagram, for receivers that do not read bundles.
`scale` sizes the body: the calibrated user's (1 / height_scale) instead of the canonical 1.75 m one.

Nothing is allocated for the wire format per frame: the packets are encoded once and only their
floats are rewritten (osc.PacketTemplate). Send errors are counted in `stats`, never raised or
logged per frame: a missing receiver must not stop the tracker.
"""
import time

import numpy as np

from edge.skeleton import JOINT_NAMES, NUM_JOINTS, OFFSETS
from firmware_bridge.outputs import to_unity_position, to_unity_quaternion
from firmware_bridge.outputs.udp import UdpSender
from firmware_bridge.outputs.osc import PacketTemplate

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 39539             # the Marionette (receiver) port of the VMC protocol

# Our joints -> Unity's HumanBodyBones names, in JOINT_NAMES order.
UNITY_BONES = {
    "pelvis": "Hips", "spine": "Spine", "chest": "Chest", "neck": "Neck", "head": "Head",
    "l_collar": "LeftShoulder", "l_shoulder": "LeftUpperArm", "l_elbow": "LeftLowerArm", "l_wrist": "LeftHand",
    "r_collar": "RightShoulder", "r_shoulder": "RightUpperArm", "r_elbow": "RightLowerArm", "r_wrist": "RightHand",
    "l_hip": "LeftUpperLeg", "l_knee": "LeftLowerLeg", "l_ankle": "LeftFoot", "l_toe": "LeftToes",
    "r_hip": "RightUpperLeg", "r_knee": "RightLowerLeg", "r_ankle": "RightFoot", "r_toe": "RightToes",
}
BONE_NAMES = tuple(UNITY_BONES[name] for name in JOINT_NAMES)

ROOT_ADDRESS = "/VMC/Ext/Root/Pos"
BONE_ADDRESS = "/VMC/Ext/Bone/Pos"
OK_ADDRESS = "/VMC/Ext/OK"
TIME_ADDRESS = "/VMC/Ext/T"
TRANSFORM_FLOATS = 7             # position xyz, quaternion xyzw
IDENTITY_TRANSFORM = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
MAX_DATAGRAM = 1472              # UDP payload of one 1,500-byte Ethernet frame (IPv4, no options)
MODES = ("split", "bundle", "messages")


def frame_messages():
    """The frame's messages as (address, args) with placeholder floats: the fixed layout."""
    placeholder = (0.0,) * TRANSFORM_FLOATS
    return ([(ROOT_ADDRESS, ("root",) + placeholder)]
            + [(BONE_ADDRESS, (bone,) + placeholder) for bone in BONE_NAMES]
            + [(OK_ADDRESS, (1,)), (TIME_ADDRESS, (0.0,))])


def split_bundles(messages, limit=MAX_DATAGRAM):
    """The messages, in order, grouped into the fewest bundles of at most `limit` bytes each."""
    groups, size = [[]], 16                             # '#bundle\0' + time tag
    for m in messages:
        need = 4 + len(PacketTemplate([m], bundle=False).buffer)
        if groups[-1] and size + need > limit:
            groups.append([])
            size = 16
        groups[-1].append(m)
        size += need
    return groups


def bone_transforms(pose, offsets=OFFSETS, out=None, scale=1.0):
    """Unity local transforms of all bones [J,7] (position xyz, quaternion xyzw) for one Pose, the
    body scaled by `scale` (offsets are expected scaled already)."""
    out = np.empty((NUM_JOINTS, TRANSFORM_FLOATS)) if out is None else out
    out[0, :3] = to_unity_position(pose.positions[0] * scale)     # Hips relative to the root at the origin
    out[1:, :3] = to_unity_position(offsets[1:])
    out[:, 3:] = to_unity_quaternion(pose.rotations)
    return out


class VmcSender(UdpSender):
    """Sends each Pose to a VMC receiver (Marionette) over UDP."""

    def __init__(self, host=DEFAULT_HOST, port=DEFAULT_PORT, mode="split", offsets=OFFSETS, scale=1.0):
        if mode not in MODES:
            raise ValueError(f"VMC mode must be one of {', '.join(MODES)}, not {mode!r}")
        super().__init__(host, port)
        self.scale = float(scale)
        self.offsets = np.asarray(offsets, dtype=np.float64) * self.scale
        messages = frame_messages()
        if mode == "bundle":
            self._packets = [PacketTemplate(messages)]
        elif mode == "split":
            self._packets = [PacketTemplate(group) for group in split_bundles(messages)]
        else:
            self._packets = [PacketTemplate([m], bundle=False) for m in messages]
        # All floats of a frame in wire order: root (7), bones (J x 7), time (1).
        self._floats = np.zeros(sum(p.float_count for p in self._packets))
        self._floats[:TRANSFORM_FLOATS] = IDENTITY_TRANSFORM
        self._bones = self._floats[TRANSFORM_FLOATS:-1].reshape(NUM_JOINTS, TRANSFORM_FLOATS)
        self._start = time.monotonic()

    def packets(self, pose, t):
        """The encoded datagrams of one frame (views of preallocated buffers, valid until the next call)."""
        bone_transforms(pose, self.offsets, out=self._bones, scale=self.scale)
        self._floats[-1] = t
        start = 0
        for packet in self._packets:
            packet.set_floats(self._floats[start:start + packet.float_count])
            start += packet.float_count
        return [packet.buffer for packet in self._packets]

    def send(self, pose, t=None):
        """Send one frame; t is the /VMC/Ext/T time in seconds (default: since this sender started)."""
        t = time.monotonic() - self._start if t is None else t
        self.send_datagrams(self.packets(pose, t))

