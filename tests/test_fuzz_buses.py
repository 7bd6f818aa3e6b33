"""Fuzzing the bus decoders that are not framed byte streams: CAN frames and BNO055 register reads.

(The serial protocol's decoders are fuzzed in test_protocol.py.) Whatever arrives, the decoder must
not raise, and whatever it lets through must be a finite, unit-length orientation.
"""
import can
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from edgetools.sim.bno055_fake import FakeBNO055, ManualClock
from firmware_bridge.transports import open_source
from firmware_bridge.wire.can_frames import TrackerFrameDecoder, encode_node_frames

FUZZ = settings(max_examples=2000, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])

frames = st.builds(
    lambda arb, ext, data, dlc, remote, error, ts: can.Message(
        arbitration_id=arb if ext else arb & 0x7FF, is_extended_id=ext, data=data, dlc=dlc,
        is_remote_frame=remote, is_error_frame=error, timestamp=ts, check=False),
    st.integers(0, 0x1FFFFFFF), st.booleans(), st.binary(max_size=8), st.integers(0, 8),
    st.booleans(), st.booleans(), st.floats(0, 1e6, allow_nan=False))


def assert_sane(sample):
    assert np.all(np.isfinite(sample.quat)) and abs(np.linalg.norm(sample.quat) - 1) < 1e-6
    assert sample.accel is None or np.all(np.isfinite(sample.accel))


@FUZZ
@given(st.lists(frames, max_size=12), st.integers(0, 255))
def test_can_decoder_survives_any_frames_and_decodes_the_next_real_pair(msgs, sequence):
    """Random frames never raise and never pass anything insane; a node's real pair after them decodes
    (so the sanity check runs in every example, not only when noise happens to form a pair)."""
    dec = TrackerFrameDecoder({1: "waist", 2: "l_foot"})
    for m in msgs:
        out = dec.feed(m, received=0.0)
        if out is not None:
            assert_sane(out)
    q = np.array([0.5, 0.5, -0.5, 0.5])
    a, b = encode_node_frames(2, q, np.array([0.1, 0.2, 0.3]), 0xFF, sequence)
    a.timestamp = b.timestamp = 2e6
    assert dec.feed(a, received=0.0) is None
    out = dec.feed(b, received=0.0)
    assert out is not None and out.tracker == "l_foot"
    assert_sane(out)
    np.testing.assert_allclose(out.quat, q, atol=1e-4)


@FUZZ
@given(st.binary(min_size=16, max_size=16), st.integers(0, 255), st.integers(0, 8))
def test_can_decoder_survives_bit_flips_in_real_frames(noise, sequence, flip_at):
    dec = TrackerFrameDecoder({1: "waist"})
    q = np.array([0.5, 0.5, 0.5, 0.5])
    a, b = encode_node_frames(1, q, np.array([0.1, 0.2, 0.3]), 0xFF, sequence)
    data = bytearray(a.data) + bytearray(b.data)
    for i in range(flip_at):
        data[noise[i] % 16] ^= 1 << (noise[i + 8] % 8)
    a.data, b.data = bytes(data[:8]), bytes(data[8:])
    for m in (a, b):
        out = dec.feed(m, received=0.0)
        if out is not None:
            assert_sane(out)


class RandomOutputBus:
    """A BNO055 whose output registers read back whatever hypothesis chooses (a failing part or bus)."""

    def __init__(self, fake, blocks):
        self.fake, self.blocks = fake, list(blocks)
        self.armed = False

    def __getattr__(self, name):
        return getattr(self.fake, name)

    def read_i2c_block_data(self, addr, register, length, force=None):
        real = self.fake.read_i2c_block_data(addr, register, length)
        if self.armed and self.blocks:
            raw = self.blocks.pop()
            return list((raw * (length // len(raw) + 1))[:length])
        return real


@settings(max_examples=2000, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.binary(min_size=1, max_size=32), min_size=1, max_size=6))
def test_bno055_source_survives_any_register_bytes(blocks):
    clock = ManualClock(start=100.0)
    bus = RandomOutputBus(FakeBNO055(clock=clock, sleep=clock.sleep), blocks)
    source = open_source("i2c://1/0x28?tracker=waist&rate=100", bus=bus, clock=clock, sleep=clock.sleep)
    bus.armed = True
    for _ in range(len(blocks) + 1):
        out = source.recv(timeout=0.05)
        if out is not None:
            assert_sane(out)
    # The bus reads true again: within a few seconds (backoff, a re-initialisation) samples come back.
    recovered = None
    for _ in range(200):
        recovered = source.recv(timeout=0.05)
        if recovered is not None:
            break
    assert recovered is not None, "no sample after the bus recovered"
    assert_sane(recovered)
    source.close()
