"""Framing of the board's serial links: COBS(body + CRC-16) then one 0x00 byte (docs beside: protocol.md).

The body is a little-endian header (version u8, type u8, seq u16, t_us u32) and the message's payload
(messages.py). A frame that fails its COBS, CRC, length, version or type raises ProtocolError; a reader
counts and drops it. The header's clock and sequence number are read back by TimestampUnwrapper and
sequence_gap.
"""
import binascii
import struct
from dataclasses import dataclass

VERSION = 1

# Message types.
TRACKER_SAMPLES = 0x01
HEADSET_POSE = 0x02
POSE_FRAME = 0x03
TARGET = 0x04
MESSAGE_TYPES = {TRACKER_SAMPLES: "TRACKER_SAMPLES", HEADSET_POSE: "HEADSET_POSE", POSE_FRAME: "POSE_FRAME",
                 TARGET: "TARGET"}

HEADER = struct.Struct("<BBHI")          # version, type, seq, t_us
CRC = struct.Struct("<H")
DELIMITER = b"\x00"
# Longest COBS-encoded frame a reader buffers (delimiter not counted). The largest legal frame, 32
# tracker samples, is 590 bytes; anything longer is noise or a lost delimiter.
MAX_ENCODED_FRAME = 1024


class ProtocolError(ValueError):
    """A frame that cannot be decoded: bad COBS, bad CRC, bad length, unknown type or version, bad value.
    `kind` says which family, for the counters: "framing" (COBS, CRC, length, version, type),
    "quaternion" (not a rotation), "range" (a position beyond POSITION_LIMIT_M), "value" (NaN, infinity,
    a field that contradicts itself)."""

    def __init__(self, message, kind="framing"):
        super().__init__(message)
        self.kind = kind


# ---------------------------------------------------------------------------------------------
# COBS (consistent overhead byte stuffing): removes every 0x00 from a frame so 0x00 can end it.


def cobs_encode(data):
    """Bytes without any 0x00. Each zero-free run becomes (len + 1, run); runs longer than 254
    bytes are cut into 254-byte blocks with code 0xFF, which carry no implied zero after them."""
    out = bytearray()
    for run in bytes(data).split(b"\x00"):
        while len(run) >= 254:
            out.append(0xFF)
            out += run[:254]
            run = run[254:]
        out.append(len(run) + 1)
        out += run
    return bytes(out)


def cobs_decode(encoded):
    """Inverse of cobs_encode; raises ProtocolError on input no encoder could have produced."""
    out = bytearray()
    i = 0
    while i < len(encoded):
        code = encoded[i]
        end = i + code
        if code == 0:
            raise ProtocolError("COBS: zero byte inside a frame")
        if end > len(encoded):
            raise ProtocolError("COBS: block runs past the end of the frame")
        block = encoded[i + 1:end]
        if 0 in block:
            raise ProtocolError("COBS: zero byte inside a frame")
        out += block
        i = end
        if code < 0xFF and i < len(encoded):
            out.append(0)
    return bytes(out)


# ---------------------------------------------------------------------------------------------
# Framing.


def crc16(data):
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor."""
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass
class Frame:
    """A frame whose COBS and CRC checked out; the payload is not decoded yet."""
    msg_type: int
    seq: int
    t_us: int
    payload: bytes


def encode_frame(msg_type, seq, t_us, payload):
    """The bytes to write on the wire, delimiter included. seq and t_us wrap (u16, u32)."""
    body = HEADER.pack(VERSION, msg_type, seq & 0xFFFF, t_us & 0xFFFFFFFF) + bytes(payload)
    return cobs_encode(body + CRC.pack(crc16(body))) + DELIMITER


def decode_frame(encoded):
    """One frame as read off the wire, without its delimiter -> Frame. Raises ProtocolError."""
    if len(encoded) > MAX_ENCODED_FRAME:
        raise ProtocolError(f"frame of {len(encoded)} bytes is longer than {MAX_ENCODED_FRAME}")
    data = cobs_decode(encoded)
    if len(data) < HEADER.size + CRC.size:
        raise ProtocolError(f"frame of {len(data)} bytes is shorter than header + CRC")
    body, (crc,) = data[:-CRC.size], CRC.unpack(data[-CRC.size:])
    if crc16(body) != crc:
        raise ProtocolError("CRC mismatch")
    version, msg_type, seq, t_us = HEADER.unpack_from(body)
    if version != VERSION:
        raise ProtocolError(f"protocol version {version}, expected {VERSION}")
    if msg_type not in MESSAGE_TYPES:
        raise ProtocolError(f"unknown message type 0x{msg_type:02x}")
    return Frame(msg_type, seq, t_us, body[HEADER.size:])


def seconds_to_us(t):
    """Seconds -> the u32 microsecond timestamp of a header (wraps every 2**32 us, ~71.6 min)."""
    return round(t * 1e6) & 0xFFFFFFFF



class TimestampUnwrapper:
    """u32 microsecond timestamps -> seconds that never decrease, and that no single frame can move.

    A step forward of up to `max_step_s` (across the u32 wrap too) is time passing. Any other step (forward
    by more: a long silence, or a corrupted frame whose CRC happened to pass; backward: the sender
    restarted its clock) is believed only when the next frame confirms it by following on within
    `max_step_s`: unwrap returns None for the frame that made it (drop it), and then either
    - the next frame follows on from it: the jump was real. Forward, the output moves on by the whole
      step; backward, it holds and follows the new clock from there (counted in `backward_jumps`);
    - or the next frame follows on from the clock before it: that one frame was wrong (`glitches`).
    `jumped` says whether the last unwrap confirmed a jump.
    """

    def __init__(self, max_step_s=1.0):
        self.max_step_us = int(max_step_s * 1e6)
        self._last_raw = None
        self._total_us = 0               # python int: never overflows
        self._suspect = None             # the raw time of a frame whose jump waits for its confirmation
        self.backward_jumps = 0
        self.forward_jumps = 0
        self.glitches = 0
        self.jumped = False

    def _step(self, a, b):
        return (b - a) & 0xFFFFFFFF

    def unwrap(self, t_us):
        """This frame's time in seconds, or None when its clock jumped and waits for the next frame."""
        self.jumped = False
        if self._last_raw is None:
            self._last_raw, self._total_us = t_us, t_us
            return self._total_us * 1e-6
        if self._suspect is not None:
            if self._step(self._suspect, t_us) <= self.max_step_us:       # it follows the jump: real
                jump = self._step(self._last_raw, self._suspect)
                if jump < 1 << 31:
                    self._total_us += jump
                    self.forward_jumps += 1
                else:
                    self.backward_jumps += 1
                self.jumped = True
                self._last_raw, self._suspect = self._suspect, None
            elif self._step(self._last_raw, t_us) <= self.max_step_us:   # it follows the old clock
                self.glitches += 1
                self._suspect = None
            else:                                                        # another jump: wait for this one
                self.glitches += 1
                self._suspect = t_us
                return None
        step = self._step(self._last_raw, t_us)
        if step > self.max_step_us:
            self._suspect = t_us
            return None
        self._total_us += step
        self._last_raw = t_us
        return self._total_us * 1e-6


def sequence_gap(last_seq, seq):
    """Frames missing between two consecutive sequence numbers (u16, wrapping). A repeat, a step
    backwards or a sender restart reads as a huge gap and counts as 0."""
    gap = (seq - last_seq - 1) & 0xFFFF
    return gap if gap < 0x8000 else 0
