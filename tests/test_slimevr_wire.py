"""The SlimeVR tracker protocol (firmware_bridge.wire.slimevr) against byte-for-byte vectors built as
the firmware builds them (firmware_bridge/wire/slimevr.md), and fuzzed: no datagram may do anything but parse or
raise WireError."""
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_bridge.wire import slimevr as w

MAC = "02:ed:9e:00:00:01"
# A tracker's discovery handshake, field by field as connection.cpp sendTrackerDiscovery writes it:
# type 3, number 0, board 2, IMU 8, MCU 2, three zero ints, build 17, "0.5.0", the MAC.
HANDSHAKE = bytes.fromhex("00000003" "0000000000000000" "00000002" "00000008" "00000002" "00000000" "00000000"
                          "00000000" "00000011" "05") + b"0.5.0" + bytes.fromhex("02ed9e000001")
# ROTATION_DATA (17), packet 5, sensor 1, data type 1, quaternion x y z w = 0, 0, 0.6, 0.8, accuracy 3.
ROTATION = bytes.fromhex("00000011" "0000000000000005" "01" "01") + struct.pack(">ffff", 0, 0, 0.6, 0.8) + b"\x03"


def test_the_handshake_vector_parses_to_the_tracker_it_describes():
    p = w.parse(HANDSHAKE)
    assert p.kind == w.HANDSHAKE and p.number == 0
    h = p.items[0]
    assert (h.board, h.imu, h.mcu, h.firmware_build, h.firmware, h.mac) == (2, 8, 2, 17, "0.5.0", MAC)
    assert w.TrackerEncoder(MAC).handshake() == HANDSHAKE


def test_the_rotation_vector_parses_to_a_unit_quaternion_wxyz():
    p = w.parse(ROTATION)
    r = p.items[0]
    assert p.number == 5 and r.sensor == 1 and r.data_type == 1 and r.accuracy == 3
    np.testing.assert_allclose(r.quat, [0.8, 0, 0, 0.6], atol=1e-7)


def test_bundles_and_legacy_rotations_carry_their_sensors():
    enc = w.TrackerEncoder(MAC)
    q0, q1 = np.array([1.0, 0, 0, 0]), np.array([0.0, 1, 0, 0])
    b = w.parse(enc.bundle([(0, q0), (1, q1)]))
    assert b.kind == w.BUNDLE and [r.sensor for r in b.items] == [0, 1]
    np.testing.assert_allclose(b.items[1].quat, q1)
    legacy = w.parse(enc.legacy_rotation(q1))
    assert legacy.kind == w.ROTATION and legacy.items[0].sensor == 0
    bat = w.parse(enc.battery(3.9, 0.72)).items[0]
    assert bat.voltage == pytest.approx(3.9) and bat.level == pytest.approx(0.72)


def test_what_the_board_answers_is_what_the_firmware_checks():
    assert w.HANDSHAKE_REPLY[0] == 3 and w.HANDSHAKE_REPLY[1:13] == b"Hey OVR =D 5" and len(w.HANDSHAKE_REPLY) == 64
    assert w.heartbeat() == bytes.fromhex("00000001" "0000000000000000")
    ack = w.sensor_info_ack(1, 1)
    assert ack[4] == 1 and ack[5] == 1          # the firmware reads the sensor at [4], its state at [5]


@pytest.mark.parametrize("bad, why", [
    (HANDSHAKE[:20], "ends after"),
    (ROTATION[:-1], "ends after"),
    (ROTATION[:14] + struct.pack(">ffff", 0, 0, 0, 0) + b"\x03", "norm"),
    (ROTATION[:14] + struct.pack(">ffff", float("nan"), 0, 0, 1) + b"\x03", "NaN"),
    (bytes.fromhex("00000011" "0000000000000005" "01" "07") + ROTATION[14:], "rotation data type"),
    (bytes.fromhex("00000003" "0000000000000009") + HANDSHAKE[12:], "non-zero packet number"),
    (bytes.fromhex("00000064" "0000000000000001" "0040") + ROTATION[:10], "does not fit"),
    (b"\x00" * 5, "datagram of 5 bytes"),
])
def test_malformed_packets_raise_a_wire_error_that_says_why(bad, why):
    with pytest.raises(w.WireError, match=why):
        w.parse(bad)


VALID = [HANDSHAKE, ROTATION, w.TrackerEncoder(MAC).bundle([(0, np.array([1.0, 0, 0, 0]))] * 3),
         w.TrackerEncoder(MAC).battery(4.0, 0.9), w.TrackerEncoder(MAC).sensor_info(0)]


@st.composite
def datagrams(draw):
    kind = draw(st.integers(0, 3))
    if kind == 0:
        return draw(st.binary(min_size=0, max_size=200))
    base = bytearray(draw(st.sampled_from(VALID)))
    if kind == 1:                                    # truncated
        return bytes(base[:draw(st.integers(0, len(base)))])
    for _ in range(draw(st.integers(1, 8))):         # bit flips
        i = draw(st.integers(0, len(base) * 8 - 1))
        base[i // 8] ^= 1 << (i % 8)
    return bytes(base)


@settings(max_examples=int(__import__("os").environ.get("EDGEPOSE_FUZZ_EXAMPLES", 2000)), deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(datagrams())
def test_fuzzed_datagrams_parse_or_raise_wire_error_and_nothing_else(data):
    try:
        p = w.parse(data)
    except w.WireError:
        return
    for item in p.items:                             # whatever parses is in range
        if isinstance(item, w.Rotation):
            assert np.isfinite(item.quat).all() and abs(np.linalg.norm(item.quat) - 1) < 1e-6
        if isinstance(item, w.Acceleration):
            assert np.abs(item.accel).max() <= 1000
