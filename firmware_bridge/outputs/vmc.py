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

One OSC bundle per frame by default (about 1.8 kB): the receiver gets the whole frame in one
datagram and applies it at once (no frame torn between two poses), and the sender makes one
system call. On loopback (the default) that is far below the 64 kB limit; over Ethernet the
kernel splits it into two IP fragments. `bundle=False` sends each message as its own datagram,
for receivers that do not read bundles.

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


def frame_messages():
    """The frame's messages as (address, args) with placeholder floats: the fixed layout."""
    placeholder = (0.0,) * TRANSFORM_FLOATS
    return ([(ROOT_ADDRESS, ("root",) + placeholder)]
            + [(BONE_ADDRESS, (bone,) + placeholder) for bone in BONE_NAMES]
            + [(OK_ADDRESS, (1,)), (TIME_ADDRESS, (0.0,))])


def bone_transforms(pose, offsets=OFFSETS, out=None):
    """Unity local transforms of all bones [J,7] (position xyz, quaternion xyzw) for one Pose."""
    out = np.empty((NUM_JOINTS, TRANSFORM_FLOATS)) if out is None else out
    out[0, :3] = to_unity_position(pose.positions[0])      # Hips relative to the root at the origin
    out[1:, :3] = to_unity_position(offsets[1:])
    out[:, 3:] = to_unity_quaternion(pose.rotations)
    return out


class VmcSender(UdpSender):
    """Sends each Pose to a VMC receiver (Marionette) over UDP."""

    def __init__(self, host=DEFAULT_HOST, port=DEFAULT_PORT, bundle=True, offsets=OFFSETS):
        super().__init__(host, port)
        self.offsets = np.asarray(offsets, dtype=np.float64)
        messages = frame_messages()
        if bundle:
            self._packets = [PacketTemplate(messages)]
        else:
            self._packets = [PacketTemplate([m], bundle=False) for m in messages]
        # All floats of a frame in wire order: root (7), bones (J x 7), time (1).
        self._floats = np.zeros(sum(p.float_count for p in self._packets))
        self._floats[:TRANSFORM_FLOATS] = IDENTITY_TRANSFORM
        self._bones = self._floats[TRANSFORM_FLOATS:-1].reshape(NUM_JOINTS, TRANSFORM_FLOATS)
        self._start = time.monotonic()

    def packets(self, pose, t):
        """The encoded datagrams of one frame (views of preallocated buffers, valid until the next call)."""
        bone_transforms(pose, self.offsets, out=self._bones)
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

