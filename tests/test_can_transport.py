"""The CAN transport through python-can's real API: two virtual buses on one channel in this process,
one playing the tracker nodes, the other read by the Source."""
import time
import uuid

import can
import numpy as np
import pytest

from firmware_bridge.samples import TrackerSample
from firmware_bridge.transports import TransportError, open_source
from firmware_bridge.transports.can_bus import bus_arguments, parse_node_map
from firmware_bridge.wire.can_frames import (TrackerFrameDecoder, TrackerNodeEncoder, classify_frame,
                                             encode_node_frames, pack_quaternion, unpack_motion, unpack_quaternion)

HALF_TURN_ABOUT_Y = np.array([np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0])


@pytest.fixture
def channel():
    return f"edgepose-test-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def nodes(channel):
    """The tracker nodes' side of the bus; keeps the timestamps we give the frames."""
    bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    yield bus
    bus.shutdown()


@pytest.fixture
def source(channel):
    with open_source(f"can://virtual/{channel}?nodes=1:waist,2:l_foot") as opened:
        yield opened


def send(bus, messages, timestamp):
    for message in messages:
        message.timestamp = timestamp
        bus.send(message)


def frame(arbitration_id, data, timestamp=0.0, **flags):
    return can.Message(arbitration_id=arbitration_id, data=bytes(data), is_extended_id=False,
                       timestamp=timestamp, **flags)


def test_samples_arrive_with_the_frames_timestamps(nodes, source):
    waist, foot = TrackerNodeEncoder(1), TrackerNodeEncoder(2)
    send(nodes, waist.frames(HALF_TURN_ABOUT_Y, [0.5, -1.25, 2.0], status=0xFB), timestamp=1000.25)
    send(nodes, foot.frames([1, 0, 0, 0], [0, 0, 9.0]), timestamp=1000.26)

    before = time.monotonic()
    first, second = source.recv(timeout=1.0), source.recv(timeout=1.0)
    assert isinstance(first, TrackerSample) and isinstance(second, TrackerSample)
    assert (first.tracker, first.t, first.status) == ("waist", 1000.25, 0xFB)
    assert first.quat == pytest.approx(HALF_TURN_ABOUT_Y, abs=1e-4)
    assert first.accel == pytest.approx([0.5, -1.25, 2.0])
    assert before <= first.received <= time.monotonic()
    assert (second.tracker, second.t) == ("l_foot", 1000.26)
    assert second.quat == pytest.approx([1, 0, 0, 0])
    assert source.stats["frames"] == 2


def test_a_stream_round_trips_within_quantisation(nodes, source):
    rng = np.random.default_rng(1)
    encoder = TrackerNodeEncoder(1)
    quats = rng.normal(size=(50, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    accels = rng.uniform(-50, 50, size=(50, 3))
    for i in range(50):
        send(nodes, encoder.frames(quats[i], accels[i]), timestamp=10.0 + i / 100)
    received = [source.recv(timeout=1.0) for _ in range(50)]
    assert [s.t for s in received] == pytest.approx(10.0 + np.arange(50) / 100)
    assert np.abs(np.array([s.quat for s in received]) - quats).max() < 1e-4
    assert np.abs(np.array([s.accel for s in received]) - accels).max() <= 0.005 + 1e-9
    assert source.stats["lost"] == 0


def test_malformed_frames_are_counted_and_dropped(nodes, source):
    good_quat, good_motion = encode_node_frames(1, [1, 0, 0, 0], [1, 2, 3], 0xFF, 0)
    send(nodes, [
        frame(0x101, bytes(6)),                                       # wrong DLC
        frame(0x181, bytes(7)),                                       # wrong DLC
        frame(0x301, bytes(8)),                                       # not a tracker frame
        frame(0x103, pack_quaternion([1, 0, 0, 0])),                  # node 3 is not in ?nodes=
        can.Message(arbitration_id=0x101, data=bytes(8), is_extended_id=True),  # extended id
        frame(0x101, np.array([16384, 16384, 0, 0], "<i2").tobytes()),  # |q| = 1.41
        good_quat, good_motion,
    ], timestamp=5.0)
    sample = source.recv(timeout=1.0)
    assert sample.accel == pytest.approx([1, 2, 3])
    assert source.recv(timeout=0.05) is None
    stats = source.stats
    assert (stats["wrong_dlc"], stats["bad_quaternion"], stats["corrupt"]) == (2, 1, 3)
    assert stats["unknown_id"] == 3
    assert stats["frames"] == 1


def test_frames_whose_partner_was_lost_are_dropped(nodes, source):
    q1, m1 = encode_node_frames(1, [1, 0, 0, 0], None, 0xFF, 1)
    q2, m2 = encode_node_frames(1, HALF_TURN_ABOUT_Y, None, 0xFF, 2)
    q3, m3 = encode_node_frames(1, [0, 1, 0, 0], None, 0xFF, 3)
    send(nodes, [m1], timestamp=1.00)          # its quaternion frame was lost
    send(nodes, [q2], timestamp=1.01)          # its motion frame was lost ...
    send(nodes, [q3, m3], timestamp=1.02)      # ... so q3 replaces it
    sample = source.recv(timeout=1.0)
    assert sample.t == 1.02 and sample.quat == pytest.approx([0, 1, 0, 0])
    assert source.stats["unpaired"] == 2


def test_a_quaternion_too_old_for_the_motion_frame_is_not_paired(nodes, source):
    q, m = encode_node_frames(1, [1, 0, 0, 0], None, 0xFF, 0)
    send(nodes, [q], timestamp=1.0)
    send(nodes, [m], timestamp=1.5)
    assert source.recv(timeout=0.1) is None
    assert source.stats["unpaired"] == 2


def test_sequence_gaps_count_lost_samples(nodes, source):
    encoder = TrackerNodeEncoder(2)
    for i in range(10):
        messages = encoder.frames([1, 0, 0, 0])
        if i not in (3, 4, 7):
            send(nodes, messages, timestamp=i / 100)
    assert len([s for s in (source.recv(timeout=0.5) for _ in range(7)) if s is not None]) == 7
    assert source.stats["lost"] == 3


def test_sequence_wraps_without_counting_losses():
    decoder = TrackerFrameDecoder()
    encoder = TrackerNodeEncoder(5)
    encoder.sequence = 250
    for i in range(12):
        for message in encoder.frames([1, 0, 0, 0]):
            message.timestamp = i / 100
            decoder.feed(message)
    assert decoder.stats["lost"] == 0 and decoder.stats["frames"] == 12


def test_nodes_without_a_map_are_named_by_id():
    decoder = TrackerFrameDecoder()
    quat_frame, motion_frame = encode_node_frames(42, [1, 0, 0, 0], None, 0, 0)
    assert decoder.feed(quat_frame) is None
    assert decoder.feed(motion_frame).tracker == "node42"


def test_error_frames_count_as_errors():
    decoder = TrackerFrameDecoder()
    assert decoder.feed(can.Message(is_error_frame=True)) is None
    assert decoder.stats["errors"] == 1


def test_recv_times_out_with_none_when_nothing_arrives(source):
    start = time.monotonic()
    assert source.recv(timeout=0.05) is None
    assert 0.04 <= time.monotonic() - start < 0.5


def test_worked_example_in_docs_matches_the_encoder():
    quat_frame, motion_frame = encode_node_frames(2, [0.70711, 0, 0.70711, 0], [0.5, -1.25, 2.0], 0xFB, 42)
    assert (quat_frame.arbitration_id, quat_frame.data.hex(" ").upper()) == (0x102, "41 2D 00 00 41 2D 00 00")
    assert (motion_frame.arbitration_id, motion_frame.data.hex(" ").upper()) == (0x182, "32 00 83 FF C8 00 FB 2A")
    assert unpack_quaternion(quat_frame.data) == pytest.approx([0.70711, 0, 0.70711, 0], abs=1e-4)
    accel, status, sequence = unpack_motion(motion_frame.data)
    assert (accel.tolist(), status, sequence) == ([0.5, -1.25, 2.0], 0xFB, 42)


def test_frame_ids_identify_kind_and_node():
    assert classify_frame(0x101) == ("quat", 1)
    assert classify_frame(0x1FF) == ("motion", 0x7F)
    assert classify_frame(0x100) == (None, None)              # node 0 is reserved
    assert classify_frame(0x201) == (None, None)
    assert classify_frame(0x101, is_extended_id=True) == (None, None)
    with pytest.raises(ValueError):
        TrackerNodeEncoder(128)


def test_url_names_the_python_can_interface_and_channel():
    assert bus_arguments("virtual", "/bus0", {}) == {"interface": "virtual", "channel": "bus0"}
    assert bus_arguments("socketcan", "/can0", {"bitrate": "500000"}) == {
        "interface": "socketcan", "channel": "can0", "bitrate": 500000}
    with pytest.raises(TransportError, match="can://socketcan/can0"):
        bus_arguments("socketcan", "", {})


def test_node_map_parses_ids_and_names():
    assert parse_node_map("1:waist, 2:l_foot,0x10:r_foot") == {1: "waist", 2: "l_foot", 16: "r_foot"}
    assert parse_node_map("") == {}
    for bad in ("waist", "0:waist", "200:x", "3:"):
        with pytest.raises(TransportError, match="ID:NAME"):
            parse_node_map(bad)


def test_an_interface_that_cannot_open_says_what_to_do():
    with pytest.raises(TransportError, match="no_such_interface"):
        open_source("can://no_such_interface/x")


def test_an_open_bus_can_be_passed_in_and_is_left_open(channel, nodes):
    bus = can.Bus(interface="virtual", channel=channel)
    with open_source("can://virtual/ignored", bus=bus) as source:
        send(nodes, encode_node_frames(1, [1, 0, 0, 0], None, 0, 0), timestamp=3.0)
        assert source.recv(timeout=1.0).t == 3.0
    bus.recv(timeout=0)                                     # still open: does not raise
    bus.shutdown()
