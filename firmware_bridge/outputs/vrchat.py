"""VRChat OSC trackers: joints of the pose as virtual full-body trackers (docs.vrchat.com, "OSC Trackers").

Per frame, each message its own datagram:
    /tracking/trackers/N/position    x y z        N = 1..8, world position, metres
    /tracking/trackers/N/rotation    x y z        world rotation, Unity Euler angles in degrees
    /tracking/trackers/head/position x y z        the headset's eye point, for alignment
    /tracking/trackers/head/rotation x y z

VRChat reads these in Unity's frame (left-handed, Y-up, 1 unit = 1 m; see firmware_bridge.outputs
for the mirror from ours). Euler angles follow Unity's Transform.eulerAngles: rotate Z degrees
about z, then X about x, then Y about y, all about the fixed axes, so R = Ry(y) @ Rx(x) @ Rz(z).
That is what VRChat's own example sender passes (Transform.eulerAngles).

Trackers: hips, chest, both feet (the ankle joint, where foot trackers are worn), both knees.
VRChat binds each tracker to a bone at calibration with whatever offset it has then, so a tracker
only needs to move rigidly with its joint; the joint's own world rotation (identity in the T-pose)
does that. VRChat's docs advise sending few trackers (feet and hips are often best); the arms
come from the controllers VRChat already has.

The head messages let VRChat align our tracking space with its own. We send the point the headset
itself reports (head joint plus edge.signals.EYE_OFFSET in the head frame), so the alignment lands
where VRChat's headset is, not 13 cm behind and below it at the base of the skull.

Separate messages rather than a bundle: it is what VRChat's example sender does and needs nothing
of the receiver. 14 datagrams of 52 bytes per frame by default. Packets are encoded once; only the floats
change (osc.PacketTemplate). Send errors are counted in `stats`, never raised or logged per frame.
"""

import numpy as np

from edge.signals import EYE_OFFSET
from edge.skeleton import HEAD, JOINT, NUM_JOINTS, fk
from firmware_bridge.outputs import to_unity_matrix, to_unity_position
from firmware_bridge.outputs.udp import UdpSender
from firmware_bridge.outputs.osc import PacketTemplate

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 9000              # VRChat's OSC input port
MAX_TRACKERS = 8
DEFAULT_TRACKERS = ("pelvis", "chest", "l_ankle", "r_ankle", "l_knee", "r_knee")
GIMBAL_EPS = 1e-9


def unity_euler_degrees(m):
    """Unity rotation matrices [...,3,3] -> Euler angles [...,3] (x, y, z) in degrees, R = Ry Rx Rz.

    Angles are in (-180, 180] (Unity itself reports [0, 360); both mean the same rotation).
    With c = cos(x): R[1,2] = -sin(x), R[0,2] = sin(y) c, R[2,2] = cos(y) c, R[1,0] = sin(z) c,
    R[1,1] = cos(z) c. At x = +-90 degrees (c = 0) only y + z or y - z is defined: we put it all in y.
    """
    cos_x = np.hypot(m[..., 1, 0], m[..., 1, 1])
    x = np.arctan2(-m[..., 1, 2], cos_x)
    gimbal = cos_x < GIMBAL_EPS
    y = np.where(gimbal, np.arctan2(-m[..., 2, 0], m[..., 0, 0]), np.arctan2(m[..., 0, 2], m[..., 2, 2]))
    z = np.where(gimbal, 0.0, np.arctan2(m[..., 1, 0], m[..., 1, 1]))
    return np.degrees(np.stack([x, y, z], axis=-1))


def tracker_messages(trackers, send_head):
    """(address, placeholder args) of every message of a frame, in the order they are sent."""
    ids = [str(k) for k in range(1, len(trackers) + 1)] + (["head"] if send_head else [])
    return [(f"/tracking/trackers/{i}/{what}", (0.0, 0.0, 0.0)) for i in ids for what in ("position", "rotation")]


class VrchatSender(UdpSender):
    """Sends chosen joints of each Pose to VRChat as OSC trackers over UDP."""

    def __init__(self, host=DEFAULT_HOST, port=DEFAULT_PORT, trackers=DEFAULT_TRACKERS, send_head=True, scale=1.0):
        """trackers: joint names (edge.skeleton), 1..8 (`[output] vrchat_trackers`); scale sizes the body:
        the calibrated user's (1 / height_scale), as VRChat's docs ask senders to account for height."""
        if not 1 <= len(trackers) <= MAX_TRACKERS:
            raise ValueError(f"VRChat takes 1..{MAX_TRACKERS} trackers, got {len(trackers)}")
        unknown = [name for name in trackers if name not in JOINT]
        if unknown:
            raise ValueError(f"unknown joint {unknown[0]!r}: trackers are joint names of edge.skeleton")
        super().__init__(host, port)
        self.scale = float(scale)
        self.trackers = tuple(trackers)
        self.send_head = send_head
        self._joints = np.array([JOINT[name] for name in trackers])
        self._packets = [PacketTemplate([m], bundle=False) for m in tracker_messages(trackers, send_head)]
        # One (position, rotation) row pair per tracker, then the head's: [K,2,3], wire order.
        self._values = np.zeros((len(self._packets) // 2, 2, 3))
        self._world_rot = np.zeros((NUM_JOINTS, 3, 3))
        self._world_pos = np.zeros((NUM_JOINTS, 3))

    def packets(self, pose):
        """The encoded datagrams of one frame (preallocated buffers, valid until the next call)."""
        # Pose carries local rotations; trackers need world ones.
        fk(pose.rotations, pose.positions[0], out=(self._world_rot, self._world_pos))
        K = len(self._joints)
        self._values[:K, 0] = to_unity_position(pose.positions[self._joints] * self.scale)
        self._values[:K, 1] = unity_euler_degrees(to_unity_matrix(self._world_rot[self._joints]))
        if self.send_head:
            head_rot = self._world_rot[HEAD]
            eyes = pose.positions[HEAD] + head_rot @ EYE_OFFSET
            self._values[K, 0] = to_unity_position(eyes * self.scale)
            self._values[K, 1] = unity_euler_degrees(to_unity_matrix(head_rot))
        for packet, values in zip(self._packets, self._values.reshape(-1, 3), strict=True):
            packet.set_floats(values)
        return [packet.buffer for packet in self._packets]

    def send(self, pose):
        self.send_datagrams(self.packets(pose))

