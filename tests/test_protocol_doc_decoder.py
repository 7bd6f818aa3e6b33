"""firmware_bridge/wire/protocol.md is enough to build a decoder: a POSE_FRAME reader written from the document alone
(struct and binascii only, nothing from firmware_bridge.wire) decodes what the real encoder sends."""
import binascii
import math
import struct

import numpy as np
import pytest


# --- an independent POSE_FRAME decoder, written from firmware_bridge/wire/protocol.md ----------------------------

def doc_cobs_decode(encoded):
    """Section 1.1. None if the COBS is invalid."""
    out = bytearray()
    i = 0
    while i < len(encoded):
        code = encoded[i]
        if code == 0 or i + code > len(encoded):
            return None
        out += encoded[i + 1:i + code]
        i += code
        if code < 0xFF and i < len(encoded):
            out.append(0)
    return bytes(out)


def doc_quaternion(raw):
    """Section 2: Q14, rejected if the norm is more than 0.05 from 1, else normalised."""
    q = [v / 16384 for v in raw]
    norm = math.sqrt(sum(v * v for v in q))
    if abs(norm - 1.0) > 0.05:
        return None
    return [v / norm for v in q]


def doc_decode_pose_frame(frame):
    """One frame without its delimiter -> dict, or None if it must be dropped (section 1.3)."""
    data = doc_cobs_decode(frame)
    if data is None or len(data) < 10:
        return None
    body, (crc,) = data[:-2], struct.unpack("<H", data[-2:])
    if binascii.crc_hqx(body, 0xFFFF) != crc:
        return None
    version, msg_type, seq, t_us = struct.unpack_from("<BBHI", body, 0)
    if version != 1 or msg_type != 0x03 or len(body) != 8 + 180:
        return None
    payload = body[8:]
    root_mm = struct.unpack_from("<3h", payload, 0)
    rotations = [doc_quaternion(struct.unpack_from("<4h", payload, 6 + 8 * j)) for j in range(21)]
    if any(q is None for q in rotations):
        return None
    contact_left, contact_right, num_samples, ssi_flags, trackers_lost = struct.unpack_from("<BBBBH", payload, 174)
    return {
        "seq": seq, "t_us": t_us,
        "root_pos": [v / 1000 for v in root_mm],
        "rotations": rotations,
        "contacts": [contact_left / 255, contact_right / 255],
        "num_samples": num_samples, "ssi_flags": ssi_flags, "trackers_lost": trackers_lost,
    }


def doc_read_pose_stream(stream):
    """Every good POSE_FRAME in a byte stream, in order."""
    frames = (doc_decode_pose_frame(frame) for frame in stream.split(b"\x00") if frame)
    return [frame for frame in frames if frame is not None]


# --- the test: the real encoder on one side, the document's decoder on the other -----------------

def pose_stream(count, seed=0):
    """(PoseFrames, the bytes the board would send for them) with some line noise between frames."""
    from edge.skeleton import NUM_JOINTS
    from firmware_bridge.wire.messages import PoseFrame, encode_pose_frame

    rng = np.random.default_rng(seed)
    frames, stream = [], bytearray()
    for k in range(count):
        rotations = rng.normal(size=(NUM_JOINTS, 4))
        frame = PoseFrame(t=100.0 + k / 60, root_pos=rng.uniform(-3, 3, 3) + [0, 0.95, 0],
                          rotations=rotations / np.linalg.norm(rotations, axis=1, keepdims=True),
                          contacts=rng.uniform(0, 1, 2), num_samples=int(rng.choice([1, 10, 100])),
                          ssi_flags=int(rng.integers(0, 8)), trackers_lost=int(rng.integers(0, 1 << 16)))
        frames.append(frame)
        stream += encode_pose_frame(frame, seq=65530 + k)
        if k % 10 == 5:
            stream += bytes(rng.integers(1, 256, 20, dtype=np.uint8)) + b"\x00"    # noise, ended by a 0x00
    return frames, bytes(stream)


def test_decoder_written_from_the_doc_reads_the_encoders_pose_stream():
    frames, stream = pose_stream(120)
    decoded = doc_read_pose_stream(stream)
    assert len(decoded) == len(frames)
    for k, (got, want) in enumerate(zip(decoded, frames, strict=True)):
        assert got["seq"] == (65530 + k) & 0xFFFF
        assert got["t_us"] == round(want.t * 1e6)
        np.testing.assert_allclose(got["root_pos"], want.root_pos, atol=0.0005 + 1e-9)
        np.testing.assert_allclose(got["rotations"], want.rotations, atol=2e-4)
        np.testing.assert_allclose(got["contacts"], want.contacts, atol=0.5 / 255 + 1e-9)
        assert (got["num_samples"], got["ssi_flags"], got["trackers_lost"]) == (
            want.num_samples, want.ssi_flags, want.trackers_lost)


def test_decoder_written_from_the_doc_agrees_with_the_reference_reader():
    from firmware_bridge.wire.messages import FrameReader

    _, stream = pose_stream(60, seed=1)
    reference = FrameReader().feed(stream)
    decoded = doc_read_pose_stream(stream)
    assert len(decoded) == len(reference) == 60
    for got, want in zip(decoded, reference, strict=True):
        assert got["t_us"] * 1e-6 == pytest.approx(want.t, abs=1e-9)
        np.testing.assert_allclose(got["rotations"], want.rotations, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(got["root_pos"], want.root_pos)
        np.testing.assert_array_equal(got["contacts"], want.contacts)


def test_decoder_written_from_the_doc_drops_what_the_doc_says_to_drop():
    _, stream = pose_stream(3, seed=2)
    first_end = stream.index(b"\x00")
    broken = bytearray(stream)
    broken[first_end - 1] ^= 0x01                   # first frame's CRC
    assert len(doc_read_pose_stream(bytes(broken))) == 2
