"""Every pose to every output: the POSE_FRAME stream back to the headset (on its own link or a port of
its own, protocol.md) and the sinks a config names (VMC, VRChat OSC, BVH), each in the calibrated
user's size. The service hands it each pose it makes; a failing output is counted, never raised.

Encoding allocates nothing per pose: one PoseFrame, one quaternion buffer bound to the pipeline's
output rotations once (native.from_matrix_bound)."""
from pathlib import Path

import numpy as np

from edge import native
from firmware_bridge.links import Link
from firmware_bridge.transports import TransportError, open_source
from firmware_bridge.wire import messages

TICK_MEMORY = 256            # input tick times kept by pipeline frame index (>= the look-ahead)


def open_sinks(cfg, size, offsets=None):
    """VMC, VRChat and BVH as the config names them, each sized `size` (1 / the calibration's height scale:
    the pipeline's body is the canonical one); the skeleton VMC's bones and the BVH are sent on,
    `offsets` (the user's legs, edge.proportions; the canonical skeleton when None). VRChat's trackers
    are positions: the pose's, already on the user's legs."""
    outs = []
    if cfg.vmc:
        from firmware_bridge.outputs.vmc import VmcSender
        host, _, port = cfg.vmc.rpartition(":")
        outs.append(VmcSender(host, int(port), mode=cfg.vmc_mode, scale=size,
                              **({} if offsets is None else {"offsets": offsets})))
    if cfg.vrchat:
        from firmware_bridge.outputs.vrchat import VrchatSender
        host, _, port = cfg.vrchat.rpartition(":")
        outs.append(VrchatSender(host, int(port), trackers=cfg.vrchat_trackers, scale=size))
    if cfg.bvh:
        from firmware_bridge.outputs.bvh_writer import BvhWriter
        Path(cfg.bvh).parent.mkdir(parents=True, exist_ok=True)
        outs.append(BvhWriter(cfg.bvh, fps=cfg.hz, scale=size, offsets=offsets))
    return outs


def body_shape(body, calibration):
    """The BODY_SHAPE text of `body` (edge.proportions.UserBody) at the calibrated user's size."""
    from firmware_bridge.wire.webxr import encode_body_shape
    return encode_body_shape(body.offsets / calibration.height_scale, calibration.stature_m(), body.legs, body.arms)


class PoseOutputs:
    """The pose stream and the sinks. `tick(index, now)` remembers when each input tick was (a pose
    that comes out later, after the look-ahead, is stamped with its own tick's time); `send` encodes
    and sends one pose and returns how long it was held."""

    def __init__(self, cfg, calibration, rotations, headset, clock, health_order, opener=open_source, status=None):
        """calibration: the user's size (edge.calibration.Calibration); with a [body] leg_length_m in
        `cfg`, every pose is sent on the user's legs (edge.proportions.UserBody). rotations: the
        pipeline's output rotation buffer (bound once); headset: the headset's Link (the pose stream's
        default way back); health_order: the sources in POSE_FRAME's lost bits' order."""
        from firmware_bridge.wiring import user_body
        height_scale = calibration.height_scale
        self.hz, self.clock, self.height_scale = cfg.hz, clock, height_scale
        self.body = user_body(cfg, calibration)
        self.health_order = health_order
        self.errors = 0
        self.port = None            # the pose stream's port of its own, when the config names one
        if cfg.pose_stream.startswith("serial://"):
            self.port = Link(cfg.pose_stream, opener)          # not there yet: reopened from send
            if self.port.start_error and status is not None:
                print(f"edge run: pose stream {cfg.pose_stream}: {self.port.start_error}; waiting for it", file=status)
        self.stream = headset if cfg.pose_stream == "headset" else self.port
        self.sinks = open_sinks(cfg, 1.0 / height_scale, None if self.body.canonical else self.body.offsets)
        # what the stream encodes: the pipeline's rotations, or the user's body's own (edge.proportions)
        self._rotations = rotations if self.body.canonical else self.body.pose.rotations
        # the page draws the body it is told (firmware_bridge.wire.webxr's BODY_SHAPE), at the user's size
        self.shape = body_shape(self.body, calibration)
        self._told = None                                    # the stream's source that has the shape
        self._tick_times = np.zeros(TICK_MEMORY)             # input tick time by pipeline frame index
        self._root = np.zeros(3)                             # the pose's root in the user's size
        self._quat = np.zeros((len(rotations), 4))           # the pose stream's quaternions
        self._to_quat = native.from_matrix_bound(self._rotations, self._quat)
        self.frame = messages.PoseFrame(0.0, np.zeros(3), np.tile([1.0, 0, 0, 0], (len(rotations), 1)), np.zeros(2))

    def tick(self, index, now):
        self._tick_times[index % TICK_MEMORY] = now

    def send(self, pose, health, newest_index, samples):
        """Encode `pose` (edge.frame.Pose) with the sources' health and N, send it everywhere; returns
        the seconds its frame was held for look-ahead (newest_index: the pipeline's newest frame)."""
        pose = self.body.on_user(pose)
        p = self.frame
        p.t = self._tick_times[pose.frame % TICK_MEMORY]      # the time the pose is of (its input tick)
        p.held_s = (newest_index - pose.frame) / self.hz      # held for look-ahead: 0 at tau = 0
        p.root_pos = np.divide(pose.positions[0], self.height_scale, out=self._root)
        if pose.rotations is self._rotations:
            self._to_quat()                                   # into self._quat, addresses bound once
        else:
            native.from_matrix(pose.rotations, self._quat)
        p.rotations = self._quat
        p.contacts = pose.contacts
        p.num_samples = samples
        p.ssi_flags = messages.SSI_IN_TRANSITION if pose.transition else 0
        lost = 0
        for i, name in enumerate(self.health_order):
            if health.lost.get(name, False):
                lost |= 1 << i
        p.trackers_lost = lost
        stream = self.stream
        if stream is self.port and stream is not None and stream.source is None:
            stream.drain(self.clock)            # a pose port that is not there (yet): retried with the backoff
        try:
            if stream is not None and stream.source is not None:
                if stream.source is not self._told:            # a link (re)opened: tell it the body first
                    self._told = stream.source
                    stream.source.tell_body(self.shape)
                stream.source.send_pose(p)
        except (TransportError, ValueError, AttributeError):
            self.errors += 1
        for out in self.sinks:
            try:
                out.send(pose)
            except (OSError, ValueError):
                self.errors += 1
        return p.held_s

    def close(self):
        if self.port is not None:
            self.port.close()
        for out in self.sinks:
            out.close()
