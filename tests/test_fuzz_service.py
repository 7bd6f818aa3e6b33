"""The whole service under hostile input: hypothesis writes valid-CRC frames with extreme finite values,
NaN and infinity bit patterns in any field, duplicated, reordered and jumping timestamps, and bursts,
into the real Service's serial links (real ptys, the real decoder, synchroniser, pipeline and pose
encoder), then clean input. After every example:
  - the service is still ticking (every tick ran, no exception);
  - every pose it sent is finite, every joint within 2.5 m of the headset position it used;
  - within 1 s (60 ticks) of clean input its poses are normal again (nothing reported lost).

The ordinary run tries a few examples; the full check is 2,000:

    EDGEPOSE_FUZZ_EXAMPLES=2000 .venv/bin/python -m pytest -q tests/test_fuzz_service.py
"""
import os
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from edge import quat
from edge.skeleton import fk
from edgetools.listen import Listener
from edgetools.sim.devices import wait_readable
from motion.takes import from_sample
from firmware_bridge import config as config_mod
from firmware_bridge.samples import HeadsetSample, TrackerSample
from firmware_bridge.service import Service
from firmware_bridge.wire.framing import HEADSET_POSE, TRACKER_SAMPLES, encode_frame
from firmware_bridge.wire.messages import HEADSET_RECORD, encode_headset_pose, encode_tracker_samples
from tests.conftest import SAMPLE

EXAMPLES = int(os.environ.get("EDGEPOSE_FUZZ_EXAMPLES", "25"))
HZ = 60.0
RECOVER_TICKS = 60          # 1 s of clean input
REACH_M = 2.5


class Board:
    """One service for every example (a board runs for days): its headset and hub links on ptys."""

    def __init__(self):
        self.head_m, head_s = os.openpty()
        self.hub_m, hub_s = os.openpty()
        self.slaves = (head_s, hub_s)
        cfg = config_mod.from_dict({
            "headset": {"url": f"serial://{os.ttyname(head_s)}?role=headset"},
            "trackers": [{"url": f"serial://{os.ttyname(hub_s)}?role=hub&trackers=0:waist"}],
            "output": {"pose_stream": "headset"},
            "runtime": {"samples": 4, "lookahead": 3, "adaptive": False, "precision": "fp32"}}, "fuzz")
        self.now = 0.0
        self.service = Service(cfg, clock=lambda: self.now, status=None, threaded=False)
        self.ear = Listener(fd=self.head_m)
        self.take = from_sample(SAMPLE)
        self.k = 0                      # clean frames sent so far (the take, looped)
        self.seq = 0
        self.used = {}                  # tick time (us) -> the headset position the service interpolated
        real_frame = self.service.sync.frame

        def recording(t, out=None):
            sig, health = real_frame(t, out)
            if sig is not None:
                self.used[int(round(t * 1e6))] = sig.head_pos[0].copy()
            return sig, health
        self.service.sync.frame = recording

    def write(self, fd, slave, data):
        os.write(fd, data)
        wait_readable(slave, len(data))        # the pty hands bytes over a moment later

    def clean(self):
        """This tick's headset report and waist sample, from the take, on the board's clock."""
        s, i = self.take.signals, self.k % self.take.frames
        self.k += 1
        self.seq = (self.seq + 1) & 0xFFFF
        h = HeadsetSample(self.now, s.head_pos[i], s.head_rot[i], s.hand_pos[i], s.hand_rot[i])
        self.write(self.head_m, self.slaves[0], encode_headset_pose(h, self.seq))
        self.write(self.hub_m, self.slaves[1], encode_tracker_samples([TrackerSample("waist", self.now, s.waist_rot[i])],
                                                                      self.seq))

    def tick(self):
        ticks = self.service.stats["ticks"]
        self.service.step(self.now)
        assert self.service.stats["ticks"] == ticks + 1          # still ticking
        self.now += 1.0 / HZ

    def poses(self):
        out, quiet = [], 0
        while quiet < 3:
            got = self.ear.poll(0.005)
            out += got
            quiet = 0 if got else quiet + 1
        return out


@pytest.fixture(scope="module")
def board():
    b = Board()
    for _ in range(120):                # settled on clean input first
        b.clean()
        b.tick()
    b.poses()
    yield b
    b.service.close()
    for fd in (b.head_m, b.hub_m):
        os.close(fd)


# --- hostile frames ---------------------------------------------------------------------------------
F32_PATTERNS = st.sampled_from([b"\x00\x00\xc0\x7f", b"\x01\x00\x80\x7f", b"\x00\x00\x80\x7f", b"\x00\x00\x80\xff",
                                struct.pack("<f", 3e38), struct.pack("<f", -3e38), struct.pack("<f", 1e6),
                                struct.pack("<f", 49.9), struct.pack("<f", 1e-42)])
TIMESTAMPS = st.one_of(st.just("now"), st.just("repeat"), st.just("back"), st.integers(0, 2**32 - 1))


HEADSET_FLOATS = (0, 4, 8, 21, 25, 29, 42, 46, 50)        # head and controller position fields (HEADSET_RECORD)
UNIT = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1).map(
    lambda q: np.round(np.array(q) / np.linalg.norm(q) * 16384).astype("<i2").tobytes())


@st.composite
def hostile_frame(draw):
    """A frame with a valid CRC: random bytes, or a valid record of the take's pose with positions set
    to extreme floats and NaN / infinity patterns, any rotations, any accelerations and sample ages."""
    kind = draw(st.sampled_from(["headset", "tracker"]))
    if kind == "headset":
        size = HEADSET_RECORD.itemsize
        payload = bytearray(draw(st.binary(min_size=size, max_size=size)))
        if draw(st.booleans()):                     # a well-formed record whose values are hostile
            payload[:] = VALID_HEADSET
            for at in draw(st.lists(st.sampled_from(HEADSET_FLOATS), max_size=4)):
                payload[at:at + 4] = draw(F32_PATTERNS)
            if draw(st.booleans()):
                payload[12:20] = draw(UNIT)
            payload[20] = payload[41] = draw(st.integers(0, 255))      # controllers tracked or not
    else:
        n = draw(st.integers(1, 4))
        payload = bytearray([n]) + bytearray(draw(st.binary(min_size=18 * n, max_size=18 * n)))
        for r in range(n):
            if draw(st.booleans()):                 # a record that decodes: waist, unit quaternion
                at = 1 + 18 * r
                payload[at] = 0
                payload[at + 4:at + 12] = draw(UNIT)
    return kind, bytes(payload), draw(TIMESTAMPS), draw(st.integers(0, 0xFFFF))


def _valid_headset():
    s = from_sample(SAMPLE).signals
    h = HeadsetSample(0.0, s.head_pos[0], s.head_rot[0], s.hand_pos[0], s.hand_rot[0])
    from firmware_bridge.wire.framing import cobs_decode
    return cobs_decode(encode_headset_pose(h, 0)[:-1])[8:-2]


VALID_HEADSET = _valid_headset()


@settings(max_examples=EXAMPLES, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(bursts=st.lists(st.lists(hostile_frame(), min_size=0, max_size=12), min_size=1, max_size=8),
       with_clean=st.booleans())
def test_the_service_survives_hostile_frames_and_recovers_within_a_second(board, bursts, with_clean):
    b = board
    for burst in bursts:
        if with_clean:                  # hostile frames mixed into good traffic, or instead of it
            b.clean()
        for kind, payload, stamp, seq in burst:
            t_us = {"now": round(b.now * 1e6), "repeat": round((b.now - 1 / HZ) * 1e6),
                    "back": round((b.now - 5.0) * 1e6)}.get(stamp, stamp) if isinstance(stamp, str) else stamp
            t_us = int(t_us) & 0xFFFFFFFF
            frame = encode_frame(HEADSET_POSE if kind == "headset" else TRACKER_SAMPLES, seq, t_us, payload)
            fd, slave = (b.head_m, b.slaves[0]) if kind == "headset" else (b.hub_m, b.slaves[1])
            b.write(fd, slave, frame)
        b.tick()
    for _ in range(RECOVER_TICKS + b.service.pipeline.lookahead + 2):
        b.clean()
        b.tick()
    poses = b.poses()
    assert poses, "the service went silent"
    assert sum(int(round(p.t * 1e6)) in b.used for p in poses) >= len(poses) - 8    # the reach check sees them
    for p in poses:
        assert np.all(np.isfinite(p.root_pos)) and np.all(np.isfinite(p.rotations))
        _, joints = fk(quat.to_matrix(p.rotations), p.root_pos)
        head = b.used.get(int(round(p.t * 1e6)))        # the headset position this pose's tick used
        if head is not None:
            assert np.linalg.norm(joints - head, axis=-1).max() <= REACH_M
    # The last poses are of ticks a second into the clean input: normal again.
    assert poses[-1].trackers_lost == 0, f"still lost after 1 s of clean input: {poses[-1].trackers_lost:#x}"
    b.used.clear()
