"""The wire protocol: framing, the three messages, the streaming reader, and firmware_bridge/wire/protocol.md's test vectors."""
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from edge.skeleton import JOINT, NUM_JOINTS
from firmware_bridge.wire.framing import (
    HEADER, HEADSET_POSE, MAX_ENCODED_FRAME, MESSAGE_TYPES, POSE_FRAME, TARGET, TRACKER_SAMPLES, ProtocolError,
    TimestampUnwrapper, cobs_decode, cobs_encode, crc16, decode_frame, encode_frame, sequence_gap,
)
from firmware_bridge.wire.messages import (
    FrameReader, PoseFrame, decode_messages, encode_headset_pose, encode_pose_frame, encode_target,
    encode_tracker_samples,
)
from firmware_bridge.wire.q14 import to_q14 as quat_to_q14
from firmware_bridge.samples import HeadsetSample, TargetSample, TrackerSample

DOC = Path(__file__).resolve().parent.parent / "firmware_bridge" / "wire" / "protocol.md"
# database=None: no .hypothesis/ folder in the working tree.
FUZZ = settings(max_examples=2000, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
S45 = np.sqrt(0.5)


# --- the example messages of firmware_bridge/wire/protocol.md ----------------------------------------------------

def example_tracker_samples():
    return [
        TrackerSample("waist", 12.345678, np.array([S45, 0.0, S45, 0.0]), np.array([0.12, -0.34, 1.5]), status=0xFF),
        TrackerSample("tracker2", 12.340678, np.array([1.0, 0.0, 0.0, 0.0]), None, status=0x3C),
    ]


def example_headset_pose():
    return HeadsetSample(t=12.35, head_pos=np.array([0.25, 1.625, -0.5]), head_rot=np.array([S45, 0.0, S45, 0.0]),
                         hand_pos=np.array([[-0.25, 1.125, 0.375], [0.0, 0.0, 0.0]]),
                         hand_rot=np.array([[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]),
                         hand_valid=np.array([True, False]))


def example_pose_frame():
    rotations = np.tile([1.0, 0.0, 0.0, 0.0], (NUM_JOINTS, 1))
    rotations[JOINT["pelvis"]] = [np.cos(np.radians(15)), 0.0, np.sin(np.radians(15)), 0.0]   # 30 deg yaw
    rotations[JOINT["l_knee"]] = [S45, S45, 0.0, 0.0]                                          # 90 deg about x
    rotations[JOINT["r_knee"]] = [np.cos(np.radians(22.5)), np.sin(np.radians(22.5)), 0.0, 0.0]  # 45 deg
    return PoseFrame(t=12.36, root_pos=np.array([0.012, 0.951, -0.347]), rotations=rotations,
                     contacts=np.array([1.0, 0.0]), num_samples=10, ssi_flags=0x03, trackers_lost=0x0004)


def example_target():
    return TargetSample(t=12.37, target_id=3, joint=JOINT["l_toe"], position=np.array([0.25, 1.5, 0.75]), radius=0.05,
                        start=0.25, duration=0.5)


EXAMPLES = {
    "TRACKER_SAMPLES": lambda: encode_tracker_samples(example_tracker_samples(), seq=7),
    "HEADSET_POSE": lambda: encode_headset_pose(example_headset_pose(), seq=300),
    "POSE_FRAME": lambda: encode_pose_frame(example_pose_frame(), seq=1000),
    "TARGET": lambda: encode_target(example_target(), seq=42),
}
EXAMPLE_VALUES = {
    "TRACKER_SAMPLES": example_tracker_samples,
    "HEADSET_POSE": lambda: [example_headset_pose()],
    "POSE_FRAME": lambda: [example_pose_frame()],
    "TARGET": lambda: [example_target()],
}


def doc_vectors():
    """{(message, 'body'|'wire'): bytes} from the ```hex MESSAGE body|wire blocks of firmware_bridge/wire/protocol.md."""
    blocks = re.findall(r"```hex (\w+) (body|wire)\n(.*?)```", DOC.read_text(encoding="utf-8"), flags=re.S)
    return {(name, kind): bytes.fromhex(text) for name, kind, text in blocks}


# --- random messages -----------------------------------------------------------------------------

def random_quat(rng, shape=()):
    q = rng.normal(size=shape + (4,))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def random_tracker_samples(rng):
    count = int(rng.integers(1, 33))
    t_newest = rng.uniform(0, 4000)
    return [TrackerSample(tracker=f"tracker{int(rng.integers(1, 256))}" if rng.random() < 0.8 else "waist",
                          t=round(t_newest - rng.uniform(0, 0.06), 6),
                          quat=random_quat(rng),
                          accel=rng.uniform(-150, 150, 3) if rng.random() < 0.8 else None,
                          status=int(rng.integers(0, 256)))
            for _ in range(count)]


def random_headset_pose(rng):
    valid = rng.random(2) < 0.7
    hand_pos = np.where(valid[:, None], rng.uniform(-3, 3, (2, 3)), 0.0)
    hand_rot = np.where(valid[:, None], random_quat(rng, (2,)), [1.0, 0.0, 0.0, 0.0])
    return HeadsetSample(t=round(rng.uniform(0, 4000), 6), head_pos=rng.uniform(-3, 3, 3), head_rot=random_quat(rng),
                         hand_pos=hand_pos, hand_rot=hand_rot, hand_valid=valid)


def random_pose_frame(rng):
    return PoseFrame(t=round(rng.uniform(0, 4000), 6), root_pos=rng.uniform(-5, 5, 3),
                     rotations=random_quat(rng, (NUM_JOINTS,)), contacts=rng.uniform(0, 1, 2),
                     num_samples=int(rng.integers(1, 256)), ssi_flags=int(rng.integers(0, 8)),
                     trackers_lost=int(rng.integers(0, 1 << 16)))


def random_wire_frame(seed):
    """One encoded frame of a random type with random content and sequence number."""
    rng = np.random.default_rng(seed)
    seq = int(rng.integers(0, 1 << 16))
    kind = int(rng.integers(3))
    if kind == 0:
        return encode_tracker_samples(random_tracker_samples(rng), seq)
    if kind == 1:
        return encode_headset_pose(random_headset_pose(rng), seq)
    return encode_pose_frame(random_pose_frame(rng), seq)


wire_frames = st.integers(0, 2**32 - 1).map(random_wire_frame)


# --- comparing messages --------------------------------------------------------------------------

Q14_ATOL = 2e-4     # Q14 rounding, then normalisation


def assert_same_message(got, want):
    assert type(got) is type(want)
    assert got.t == pytest.approx(want.t, abs=1e-6)
    if isinstance(want, TrackerSample):
        assert (got.tracker, got.status) == (want.tracker, want.status)
        np.testing.assert_allclose(got.quat, want.quat, atol=Q14_ATOL)
        if want.accel is None:
            assert got.accel is None
        else:
            np.testing.assert_allclose(got.accel, want.accel, atol=0.005 + 1e-9)
    elif isinstance(want, HeadsetSample):
        np.testing.assert_allclose(got.head_pos, np.float32(want.head_pos), rtol=0, atol=0)
        np.testing.assert_allclose(got.head_rot, want.head_rot, atol=Q14_ATOL)
        np.testing.assert_array_equal(got.hand_valid, want.hand_valid)
        for hand in np.flatnonzero(want.hand_valid):
            np.testing.assert_array_equal(got.hand_pos[hand], np.float32(want.hand_pos[hand]))
            np.testing.assert_allclose(got.hand_rot[hand], want.hand_rot[hand], atol=Q14_ATOL)
    elif isinstance(want, TargetSample):
        assert (got.target_id, got.joint, got.clear) == (want.target_id, want.joint, want.clear)
        np.testing.assert_array_equal(got.position, np.float32(want.position))
        assert got.radius == np.float32(want.radius)
        assert (got.start, got.duration) == (want.start, want.duration)
    else:
        np.testing.assert_allclose(got.root_pos, want.root_pos, atol=0.0005 + 1e-9)
        np.testing.assert_allclose(got.rotations, want.rotations, atol=Q14_ATOL)
        np.testing.assert_allclose(got.contacts, want.contacts, atol=0.5 / 255 + 1e-9)
        assert (got.num_samples, got.ssi_flags, got.trackers_lost) == (want.num_samples, want.ssi_flags,
                                                                        want.trackers_lost)


def assert_well_formed(message):
    """What every decoded message guarantees: finite numbers and unit quaternions."""
    if isinstance(message, TrackerSample):
        quats = [message.quat]
        assert message.accel is None or np.all(np.isfinite(message.accel))
    elif isinstance(message, HeadsetSample):
        quats = [message.head_rot, *message.hand_rot]
        assert np.all(np.isfinite(message.head_pos)) and np.all(np.isfinite(message.hand_pos))
    elif isinstance(message, TargetSample):      # a request, decoded as sent: the refiner judges its values
        assert 0 <= message.joint <= 255 and 0 <= message.target_id <= 255 and message.position.shape == (3,)
        assert 0 <= message.start <= 65.535 and 0 <= message.duration <= 65.535
        return
    else:
        quats = list(message.rotations)
        assert np.all(np.isfinite(message.root_pos))
    np.testing.assert_allclose(np.linalg.norm(quats, axis=-1), 1.0, atol=1e-9)


def decode_one_wire_frame(wire):
    assert wire.endswith(b"\x00") and wire.count(0) == 1
    return decode_messages(decode_frame(wire[:-1]))


def crc_bitwise(data):
    """CRC-16/CCITT-FALSE from its definition, bit by bit (poly 0x1021, init 0xFFFF, MSB first, no
    reflection, no final xor): an oracle independent of binascii, which the code uses."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def crc_checks(piece):
    """Oracle: does this 0x00-free piece COBS-decode to a body whose CRC matches?"""
    try:
        data = cobs_decode(piece)
    except ProtocolError:
        return False
    return len(data) >= 10 and crc_bitwise(data[:-2]) == struct.unpack("<H", data[-2:])[0]


def reencode(body_and_crc):
    return cobs_encode(body_and_crc) + b"\x00"


# --- COBS and CRC --------------------------------------------------------------------------------

@pytest.mark.parametrize("data, encoded", [
    ("00", "0101"), ("0000", "010101"), ("11220033", "0311220233"), ("11223344", "0511223344"),
    ("11000000", "0211010101"), ("", "01"),
])
def test_cobs_matches_published_examples(data, encoded):
    assert cobs_encode(bytes.fromhex(data)) == bytes.fromhex(encoded)
    assert cobs_decode(bytes.fromhex(encoded)) == bytes.fromhex(data)


@pytest.mark.parametrize("length", [253, 254, 255, 508, 509, 600])
def test_cobs_round_trips_long_zero_free_runs(length):
    data = bytes((i % 255) + 1 for i in range(length)) + b"\x00\x07" + bytes(range(1, 255))
    encoded = cobs_encode(data)
    assert 0 not in encoded
    assert cobs_decode(encoded) == data


@given(st.binary(max_size=700))
@settings(max_examples=300, deadline=None, database=None)
def test_cobs_round_trips_any_bytes(data):
    encoded = cobs_encode(data)
    assert 0 not in encoded
    assert len(encoded) <= len(data) + 1 + len(data) // 254
    assert cobs_decode(encoded) == data


def test_crc_is_ccitt_false():
    assert crc16(b"123456789") == crc_bitwise(b"123456789") == 0x29B1      # the catalogue's check value
    rng = np.random.default_rng(5)
    for n in (0, 1, 7, 64, 591):
        data = rng.bytes(n)
        assert crc16(data) == crc_bitwise(data)


# --- round trips ---------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(50))
def test_tracker_samples_round_trip(seed):
    samples = random_tracker_samples(np.random.default_rng(seed))
    for got, want in zip(decode_one_wire_frame(encode_tracker_samples(samples, seed)), samples, strict=True):
        assert_same_message(got, want)


@pytest.mark.parametrize("seed", range(50))
def test_headset_pose_round_trips(seed):
    sample = random_headset_pose(np.random.default_rng(seed))
    [got] = decode_one_wire_frame(encode_headset_pose(sample, seed))
    assert_same_message(got, sample)


@pytest.mark.parametrize("seed", range(50))
def test_pose_frame_round_trips(seed):
    frame = random_pose_frame(np.random.default_rng(seed))
    [got] = decode_one_wire_frame(encode_pose_frame(frame, seed))
    assert_same_message(got, frame)


def test_untracked_controller_arrives_as_origin_and_identity_whatever_was_sent():
    sample = example_headset_pose()
    sample.hand_pos[1] = [np.nan, 5.0, 5.0]
    sample.hand_rot[1] = [0.0, 0.0, 0.0, 0.0]
    [got] = decode_one_wire_frame(encode_headset_pose(sample, 0))
    assert not got.hand_valid[1]
    np.testing.assert_array_equal(got.hand_pos[1], 0.0)
    np.testing.assert_array_equal(got.hand_rot[1], [1.0, 0.0, 0.0, 0.0])


def test_pose_frame_root_saturates_instead_of_wrapping():
    frame = example_pose_frame()
    frame.root_pos = np.array([40.0, -40.0, 1.0])
    [got] = decode_one_wire_frame(encode_pose_frame(frame, 0))
    np.testing.assert_allclose(got.root_pos, [32.767, -32.767, 1.0])


def test_frame_sizes_match_the_documented_budget():
    assert len(EXAMPLES["POSE_FRAME"]()) == 192
    assert len(EXAMPLES["HEADSET_POSE"]()) == 74
    assert len(encode_tracker_samples(example_tracker_samples()[:1], 0)) == 31


@pytest.mark.parametrize("bad", [
    lambda f: setattr(f, "root_pos", np.array([np.nan, 0.0, 0.0])),
    lambda f: f.rotations.__setitem__(3, np.zeros(4)),
    lambda f: setattr(f, "num_samples", 256),
    lambda f: setattr(f, "trackers_lost", 1 << 16),
    lambda f: setattr(f, "rotations", f.rotations[:20]),
])
def test_pose_frame_encoder_refuses_values_the_wire_cannot_carry(bad):
    frame = example_pose_frame()
    bad(frame)
    with pytest.raises(ValueError):
        encode_pose_frame(frame, 0)


def test_tracker_encoder_refuses_samples_too_far_apart_or_unnamed():
    samples = example_tracker_samples()
    samples[1].t -= 0.1
    with pytest.raises(ValueError, match="age"):
        encode_tracker_samples(samples, 0)
    with pytest.raises(ValueError, match="tracker_names"):
        encode_tracker_samples([TrackerSample("l_foot", 0.0, np.array([1.0, 0, 0, 0]))], 0)
    named = encode_tracker_samples([TrackerSample("l_foot", 0.0, np.array([1.0, 0, 0, 0]))], 0,
                                   tracker_names={0: "waist", 1: "l_foot"})
    [got] = FrameReader(tracker_names={0: "waist", 1: "l_foot"}).feed(named)
    assert got.tracker == "l_foot"


# --- the test vectors of firmware_bridge/wire/protocol.md --------------------------------------------------------

@pytest.mark.parametrize("name", EXAMPLES)
def test_doc_test_vector_is_what_the_encoder_writes(name):
    vectors = doc_vectors()
    wire = EXAMPLES[name]()
    assert vectors[(name, "wire")] == wire, f"firmware_bridge/wire/protocol.md {name} wire bytes differ: {wire.hex(' ')}"
    assert vectors[(name, "body")] == cobs_decode(wire[:-1]), f"firmware_bridge/wire/protocol.md {name} body bytes differ"


@pytest.mark.parametrize("name", EXAMPLES)
def test_doc_test_vector_decodes_to_the_documented_values(name):
    got = FrameReader().feed(doc_vectors()[(name, "wire")])
    for message, want in zip(got, EXAMPLE_VALUES[name](), strict=True):
        assert_same_message(message, want)


# --- the streaming reader ------------------------------------------------------------------------

def frame_with_payload(msg_type, payload):
    """A frame with a correct CRC around a payload of our choosing (to reach the value checks)."""
    return encode_frame(msg_type, 0, 0, payload)


def pose_payload():
    return decode_frame(EXAMPLES["POSE_FRAME"]()[:-1]).payload


def headset_payload():
    return decode_frame(EXAMPLES["HEADSET_POSE"]()[:-1]).payload


def with_bytes(payload, offset, data):
    return payload[:offset] + data + payload[offset + len(data):]


CORRUPT_FRAMES = {
    "bad crc": lambda: reencode(flip_last_byte(cobs_decode(EXAMPLES["POSE_FRAME"]()[:-1]))),
    "bad cobs": lambda: b"\x05\x01\x02\x00",
    "too short": lambda: reencode(b"\x01\x03\x00"),
    "random garbage": lambda: bytes(range(1, 200)) + b"\x00",
    "unknown version": lambda: reencode(with_crc(b"\x02" + cobs_decode(EXAMPLES["POSE_FRAME"]()[:-1])[1:-2])),
    "unknown type": lambda: frame_with_payload(0x7E, b""),
    "pose payload too short": lambda: frame_with_payload(POSE_FRAME, pose_payload()[:-1]),
    "pose payload too long": lambda: frame_with_payload(POSE_FRAME, pose_payload() + b"\x00"),
    "tracker count zero": lambda: frame_with_payload(TRACKER_SAMPLES, b"\x00"),
    "tracker count disagrees with length": lambda: frame_with_payload(TRACKER_SAMPLES, b"\x02" + bytes(18)),
    "quaternion far from unit": lambda: frame_with_payload(POSE_FRAME, with_bytes(pose_payload(), 6, b"\x00\x30")),
    "zero quaternion": lambda: frame_with_payload(POSE_FRAME, with_bytes(pose_payload(), 14, bytes(8))),
    "nan head position": lambda: frame_with_payload(HEADSET_POSE, with_bytes(headset_payload(), 4,
                                                                            struct.pack("<f", np.nan))),
    "infinite controller position": lambda: frame_with_payload(HEADSET_POSE, with_bytes(headset_payload(), 21,
                                                                                       struct.pack("<f", np.inf))),
    "half-missing acceleration": lambda: frame_with_payload(
        TRACKER_SAMPLES, b"\x01" + bytes(4) + struct.pack("<4h3h", 16384, 0, 0, 0, -32768, 0, 0)),
}


def flip_last_byte(data):
    return data[:-1] + bytes([data[-1] ^ 0xFF])


def with_crc(body):
    return body + struct.pack("<H", crc16(body))


@pytest.mark.parametrize("case", CORRUPT_FRAMES)
def test_corrupt_frame_is_counted_and_dropped_and_the_next_frame_decodes(case):
    reader = FrameReader()
    good = EXAMPLES["POSE_FRAME"]()
    messages = reader.feed(good + CORRUPT_FRAMES[case]() + good)
    assert len(messages) == 2
    assert_same_message(messages[1], example_pose_frame())
    assert reader.stats["corrupt"] == 1 and reader.stats["frames"] == 2
    assert reader.last_error


def test_quaternion_slightly_off_unit_is_normalised():
    payload = with_bytes(pose_payload(), 6, struct.pack("<4h", 16600, 0, 0, 0))   # norm 1.013
    [frame] = FrameReader().feed(frame_with_payload(POSE_FRAME, payload))
    np.testing.assert_allclose(frame.rotations[0], [1.0, 0.0, 0.0, 0.0])


def test_frames_of_types_the_reader_does_not_accept_are_counted_as_unexpected():
    reader = FrameReader(accept=[TRACKER_SAMPLES])
    assert reader.feed(EXAMPLES["POSE_FRAME"]() + EXAMPLES["HEADSET_POSE"]()) == []
    assert reader.stats["unexpected"] == 2 and reader.stats["corrupt"] == 0
    assert len(reader.feed(EXAMPLES["TRACKER_SAMPLES"]())) == 2


def test_bytes_fed_one_at_a_time_decode_like_one_chunk():
    # each random frame twice: its random time is a clock jump that the second copy confirms
    stream = b"".join(2 * random_wire_frame(seed) for seed in range(20))
    whole = FrameReader().feed(stream)
    reader = FrameReader()
    pieces = [m for i in range(len(stream)) for m in reader.feed(stream[i:i + 1])]
    assert len(pieces) == len(whole) >= 20
    for got, want in zip(pieces, whole, strict=True):
        assert_same_message(got, want)


def test_leading_and_repeated_delimiters_are_ignored():
    reader = FrameReader()
    messages = reader.feed(b"\x00\x00" + EXAMPLES["HEADSET_POSE"]() + b"\x00\x00")
    assert len(messages) == 1 and reader.stats["corrupt"] == 0


def test_frame_that_never_ends_is_counted_once_and_the_reader_recovers():
    reader = FrameReader()
    for _ in range(5):
        assert reader.feed(b"\x11" * 400) == []
    assert reader.stats["corrupt"] == 1
    assert reader.feed(b"\x22" * 10 + b"\x00") == []          # the tail of the endless frame
    assert len(reader.feed(EXAMPLES["POSE_FRAME"]())) == 1
    assert reader.stats["corrupt"] == 1 and len(reader._pending) == 0


def test_reader_joining_mid_frame_drops_the_partial_frame():
    wire = EXAMPLES["POSE_FRAME"]()
    reader = FrameReader()
    assert len(reader.feed(wire[50:] + wire)) == 1
    assert reader.stats["corrupt"] == 1


def test_sequence_gaps_count_missed_frames():
    sample = example_headset_pose()
    reader = FrameReader()
    for seq in (65533, 65534, 1, 2, 2, 0):                     # 65535 and 0 missing; a repeat; a restart
        reader.feed(encode_headset_pose(sample, seq))
    assert reader.stats["missed"] == 2
    assert sequence_gap(10, 11) == 0 and sequence_gap(10, 14) == 3 and sequence_gap(10, 9) == 0


# --- timestamps ----------------------------------------------------------------------------------

def test_unwrapped_time_runs_on_across_the_u32_wrap():
    clock = TimestampUnwrapper()
    raw = [2**32 - 20_000, 2**32 - 3_000, 13_000, 30_000]
    assert [clock.unwrap(t) for t in raw] == pytest.approx([4294.947296, 4294.964296, 4294.980296, 4294.997296])
    assert clock.backward_jumps == 0


def test_clock_going_backwards_is_counted_and_never_decreases_the_output():
    """A sender that restarts its clock: the frame that jumps back is dropped until the next one follows
    on from it, then the output holds and follows the new clock."""
    clock = TimestampUnwrapper()
    times = [clock.unwrap(t) for t in (5_000_000, 5_016_000, 4_000_000, 4_016_000, 10, 16_010)]
    assert times == [pytest.approx(5.0), pytest.approx(5.016), None, pytest.approx(5.032), None, pytest.approx(5.048)]
    assert clock.backward_jumps == 2 and clock.glitches == 0
    kept = [t for t in times if t is not None]
    assert all(b >= a for a, b in zip(kept, kept[1:], strict=False))


def test_a_long_silence_moves_the_clock_on_once_the_next_frame_confirms_it():
    clock = TimestampUnwrapper()
    times = [clock.unwrap(t) for t in (1_000_000, 1_016_000, 601_016_000, 601_032_000)]
    assert times == [pytest.approx(1.0), pytest.approx(1.016), None, pytest.approx(601.032)]
    assert clock.forward_jumps == 1


@pytest.mark.parametrize("wrong_us", [2**31 - 1, 1_016_000 + 2**31 + 5, 1_016_000 ^ (0b101101 << 22), 3_000_000])
def test_one_frame_whose_time_is_wrong_moves_the_clock_not_at_all(wrong_us):
    """A corrupted frame whose CRC passes can carry any time: a 35-minute leap, a step across the wrap,
    a few flipped bits. The frames after it follow the old clock, so it alone is dropped."""
    clock = TimestampUnwrapper()
    raw = [1_000_000, 1_016_000, wrong_us, 1_032_000, 1_048_000]
    times = [clock.unwrap(t) for t in raw]
    assert times == [pytest.approx(1.0), pytest.approx(1.016), None, pytest.approx(1.032), pytest.approx(1.048)]
    assert clock.glitches == 1 and clock.backward_jumps == 0 and clock.forward_jumps == 0


def test_a_crc_passing_frame_with_a_wrong_time_is_dropped_and_the_stream_keeps_its_clock():
    """The case hypothesis found on the wire: a frame whose flipped bits (here in the timestamp) still
    pass the CRC. Its messages are dropped and counted; the good frames after it keep their times."""
    sample = example_headset_pose()
    reader = FrameReader()
    times = []
    for k, t in enumerate((10.000, 10.016, 10.016 + 2**31 * 1e-6, 10.032, 10.048)):
        sample.t = t
        times += [m.t for m in reader.feed(encode_headset_pose(sample, k))]
    assert times == pytest.approx([10.000, 10.016, 10.032, 10.048], abs=1e-6)
    assert reader.stats["clock_unconfirmed"] == 1 and reader.stats["clock_jumps"] == 0


def test_reader_stamps_messages_on_the_unwrapped_clock():
    sample = example_headset_pose()
    reader = FrameReader()
    times = []
    for k, t in enumerate((4294.96, 4294.97, 4294.98)):        # crosses 2**32 us = 4294.967296 s
        sample.t = t
        times += [m.t for m in reader.feed(encode_headset_pose(sample, k))]
    assert times == pytest.approx([4294.96, 4294.97, 4294.98], abs=1e-6)
    assert reader.stats["clock_jumps"] == 0


def test_tracker_sample_time_is_frame_time_minus_its_age():
    [waist, other] = FrameReader().feed(EXAMPLES["TRACKER_SAMPLES"]())
    assert (waist.t, other.t) == pytest.approx((12.345678, 12.340678), abs=1e-9)


# --- fuzzing -------------------------------------------------------------------------------------

def feed_and_check(reader, stream):
    """Feed each 0x00-terminated piece separately: a piece may only yield messages if its CRC checks."""
    for piece in stream.split(b"\x00")[:-1]:
        messages = reader.feed(piece + b"\x00")
        if messages:
            assert crc_checks(piece)
        for message in messages:
            assert_well_formed(message)


@FUZZ
@given(st.binary(max_size=3000), st.lists(st.integers(1, 64), max_size=100))
def test_fuzz_random_bytes_in_random_chunks_never_raise(data, cuts):
    reader = FrameReader()
    position = 0
    for size in cuts + [len(data)]:
        for message in reader.feed(data[position:position + size]):
            assert_well_formed(message)
        position += size
    feed_and_check(FrameReader(), data + b"\x00")


@FUZZ
@given(wire_frames, st.data())
def test_fuzz_truncated_frame_is_dropped_and_the_next_frame_decodes(wire, data):
    cut = data.draw(st.integers(0, len(wire) - 2))
    reader = FrameReader()
    feed_and_check(reader, wire[:cut] + b"\x00")
    [got] = reader.feed(EXAMPLES["HEADSET_POSE"]())
    assert_same_message(got, example_headset_pose())


@FUZZ
@given(wire_frames, st.data())
def test_fuzz_up_to_three_flipped_bits_in_a_frame_are_always_caught(wire, data):
    # CRC-16/CCITT-FALSE has Hamming distance 4 at these lengths: 1..3 bit errors never pass.
    body = bytearray(cobs_decode(wire[:-1]))
    positions = data.draw(st.lists(st.integers(0, 8 * len(body) - 1), min_size=1, max_size=3, unique=True))
    for bit in positions:
        body[bit // 8] ^= 1 << (bit % 8)
    reader = FrameReader()
    assert reader.feed(reencode(bytes(body))) == []
    assert reader.stats == {"frames": 0, "corrupt": 1, "corrupt_framing": 1, "unexpected": 0, "missed": 0,
                            "clock_jumps": 0, "clock_unconfirmed": 0}
    assert len(reader.feed(wire)) >= 1


@FUZZ
@given(wire_frames, st.data())
def test_fuzz_flipped_bits_on_the_wire_never_yield_a_frame_whose_crc_fails(wire, data):
    encoded = bytearray(wire[:-1])
    positions = data.draw(st.lists(st.integers(0, 8 * len(encoded) - 1), min_size=1, max_size=8, unique=True))
    for bit in positions:
        encoded[bit // 8] ^= 1 << (bit % 8)
    reader = FrameReader()
    feed_and_check(reader, bytes(encoded) + b"\x00")
    [got] = reader.feed(EXAMPLES["HEADSET_POSE"]())
    # The reader is in step again. Its time is the message's own unless a corrupted piece passed the
    # CRC-16 (about 2^-16 of them: random_wire_frame(0) with bits 77, 81, 320, 323, 473 and 583 flipped
    # does, 2165.8 s), whose timestamp the unwrapper then took for the device's clock.
    want = example_headset_pose()
    if any(crc_checks(piece) for piece in bytes(encoded).split(b"\x00")):
        want.t = got.t
    assert_same_message(got, want)


PAYLOAD_SIZES = {TRACKER_SAMPLES: st.integers(0, 600), HEADSET_POSE: st.sampled_from([0, 61, 62, 63]),
                 POSE_FRAME: st.sampled_from([0, 179, 180, 181]), TARGET: st.sampled_from([0, 23, 24, 25])}


@pytest.mark.parametrize("msg_type", [TRACKER_SAMPLES, HEADSET_POSE, POSE_FRAME, TARGET], ids=MESSAGE_TYPES.values())
@FUZZ
@given(data=st.data())
def test_fuzz_payload_decoders_never_raise_and_only_yield_sane_values(msg_type, data):
    size = data.draw(PAYLOAD_SIZES[msg_type])
    if msg_type == TRACKER_SAMPLES and data.draw(st.booleans()):
        count = data.draw(st.integers(1, 32))         # a consistent count, so values get checked
        payload = bytes([count]) + data.draw(st.binary(min_size=18 * count, max_size=18 * count))
    else:
        payload = data.draw(st.binary(min_size=size, max_size=size))
    reader = FrameReader()
    for message in reader.feed(frame_with_payload(msg_type, payload)):
        assert_well_formed(message)
    assert reader.stats["frames"] + reader.stats["corrupt"] == 1


def test_header_layout_is_eight_bytes():
    assert HEADER.size == 8 and MAX_ENCODED_FRAME >= 590
    assert quat_to_q14([1.0, 0.0, 0.0, 0.0]).tolist() == [16384, 0, 0, 0]


@pytest.mark.parametrize("position, kind", [([3e38, 1.6, 0.0], "range"), ([0.0, 31.0, 0.0], "range"),
                                             ([0.0, float("nan"), 0.0], "value")])
def test_a_headset_position_beyond_any_tracked_space_is_dropped_and_counted_by_kind(position, kind):
    """A valid-CRC frame whose head position is finite but huge is corrupt, counted as `range`."""
    good = HeadsetSample(1.0, np.array([0.0, 1.6, 0.0]), np.array([1.0, 0, 0, 0]), np.zeros((2, 3)),
                         np.tile([1.0, 0, 0, 0], (2, 1)))
    bad = HeadsetSample(1.0, np.zeros(3), good.head_rot, good.hand_pos, good.hand_rot)
    payload = bytearray(HEADSET_RECORD_FOR_TEST(bad))
    payload[0:12] = np.array(position, "<f4").tobytes()
    reader = FrameReader()
    out = reader.feed(encode_headset_pose(good, 1) + encode_frame(HEADSET_POSE, 2, 2_000_000, bytes(payload)))
    assert len(out) == 1 and reader.stats["corrupt"] == 1 and reader.stats[f"corrupt_{kind}"] == 1


def HEADSET_RECORD_FOR_TEST(sample):
    """The HEADSET_POSE payload of a sample (the encoder's record, without its framing)."""
    return cobs_decode(encode_headset_pose(sample, 0)[:-1])[HEADER.size:-2]


def test_a_target_is_decoded_as_sent_so_the_board_can_say_why_it_refuses_it():
    """TARGET's floats are a request: a NaN position reaches the service (which refuses it with the
    reason non_finite, tests/test_service.py) instead of vanishing as a corrupt frame."""
    bad = example_target()
    bad.position = np.array([np.nan, 1.0, 0.0])
    [got] = FrameReader().feed(encode_target(bad, seq=1))
    assert isinstance(got, TargetSample) and np.isnan(got.position[0])
    cleared = example_target()
    cleared.clear = True
    [got] = FrameReader().feed(encode_target(cleared, seq=2))
    assert got.clear and got.target_id == 3


def test_a_signalling_nan_in_a_target_is_decoded_without_a_warning():
    """Bytes from the wire are untrusted and must not make the board print: a float32 signalling NaN
    (0x7f800001) in a TARGET's position decodes quietly to NaN (refused later as non-finite)."""
    import warnings
    from firmware_bridge.wire.messages import TARGET_RECORD, decode_target
    raw = bytearray(np.zeros((), TARGET_RECORD).tobytes())
    at = TARGET_RECORD.fields["position_m"][1]
    raw[at:at + 4] = bytes.fromhex("0100807f")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = decode_target(bytes(raw))
    assert np.isnan(got.position[0])
