"""The messages of the WebXR headset link: the board's page <-> the board over one WebSocket (protocol.md s. 9).

    page  -> board   XR_POSE   (0x02, binary)  head and both controllers' grip poses, every XR frame
    board -> page    XR_BODY   (0x03, binary)  the body the board made, with the page time it stands for
    board -> page    CLOCK_PING (0x20, binary) the board's clock; the page answers at once with
    page  -> board   CLOCK_PONG (0x21, binary) that value and the page's clock, so the board maps page time
    page  -> board   HELLO (text JSON)         {"code": "123456"} to pair, or {"token": "..."} once paired
    board -> page    WELCOME (text JSON)       {"welcome": 1, "token": ..., "board": ..., "hz": ...}
    board -> page    BODY_SHAPE (text JSON)    {"body_shape": 1, "offsets": [[x, y, z] x 21], "stature_m": ...,
                                               "legs": ..., "arms": ...}: the user's body the XR_BODYs are posed
                                               on, after WELCOME and whenever it changes

Each binary message starts with its type byte; WebSocket frames the messages, TLS protects them, so
there is no COBS or CRC here. XR_POSE and XR_BODY carry the serial link's HEADSET_POSE and POSE_FRAME
payloads unchanged (one decoder, one set of value checks: messages.py). Every message from the page is
untrusted: the decoders raise ProtocolError (with a `kind` for the counters) and never anything else.
"""
import json
import math
import struct

import numpy as np

from edge.skeleton import NUM_JOINTS
from firmware_bridge.wire.framing import ProtocolError
from firmware_bridge.wire.messages import HEADSET_RECORD, POSE_RECORD, decode_headset_pose

XR_POSE = 0x02
XR_BODY = 0x03
CLOCK_PING = 0x20
CLOCK_PONG = 0x21

XR_POSE_HEADER = struct.Struct("<BBHd")          # type, flags (0), seq, page time ms
XR_BODY_HEADER = struct.Struct("<BBHd")          # type, flags (0), seq, page time ms of the newest XR_POSE
CLOCK_PING_MSG = struct.Struct("<Bd")            # type, board time ms
CLOCK_PONG_MSG = struct.Struct("<Bdd")           # type, board time ms (echoed), page time ms
XR_POSE_SIZE = XR_POSE_HEADER.size + HEADSET_RECORD.itemsize      # 74
XR_BODY_SIZE = XR_BODY_HEADER.size + POSE_RECORD.itemsize         # 192
# A page's clock (performance.now(), ms since the page loaded) is never negative and, for a page open
# less than ten years, below this: anything else is a forged or broken value.
PAGE_TIME_LIMIT_MS = 10 * 365.25 * 86400e3
MAX_TEXT = 256                                   # the longest HELLO a page sends is ~80 bytes
CODE_DIGITS = 6
SHAPE_LIMIT_M = 1.0                              # no bone of a person 2.5 m tall is longer


def decode_xr_pose(data):
    """An XR_POSE message -> (seq, page time ms, HeadsetSample with t = page time in seconds)."""
    if len(data) != XR_POSE_SIZE:
        raise ProtocolError(f"XR_POSE is {len(data)} bytes, expected {XR_POSE_SIZE}")
    kind, flags, seq, page_ms = XR_POSE_HEADER.unpack_from(data)
    if flags:
        raise ProtocolError(f"XR_POSE flags {flags:#04x}: reserved bits set", "value")
    check_page_time(page_ms)
    sample = decode_headset_pose(bytes(data[XR_POSE_HEADER.size:]), page_ms / 1000.0)
    return seq, page_ms, sample


def encode_xr_pose(seq, page_ms, headset_payload):
    """What the page sends (the reference for its encoder): header + the 62-byte HEADSET_POSE payload."""
    if len(headset_payload) != HEADSET_RECORD.itemsize:
        raise ValueError(f"a HEADSET_POSE payload is {HEADSET_RECORD.itemsize} bytes, not {len(headset_payload)}")
    return XR_POSE_HEADER.pack(XR_POSE, 0, seq & 0xFFFF, page_ms) + bytes(headset_payload)


def encode_xr_body_into(buffer, seq, page_ms, pose_payload):
    """Fill `buffer` (XR_BODY_SIZE bytes, reused every frame) with one XR_BODY message."""
    XR_BODY_HEADER.pack_into(buffer, 0, XR_BODY, 0, seq & 0xFFFF, page_ms)
    buffer[XR_BODY_HEADER.size:] = pose_payload


def encode_body_shape(offsets, stature_m, legs=1.0, arms=1.0):
    """BODY_SHAPE: the rest offsets [J,3] of the body the XR_BODYs are posed on, metres at the user's size
    (edge.proportions' limbs scaled by the calibration), so the page draws the user's own body rather
    than the canonical one; the stature and the limbs against the canonical body's, for its panel."""
    offsets = np.asarray(offsets, dtype=np.float64)
    if offsets.shape != (NUM_JOINTS, 3) or not np.isfinite(offsets).all() or np.abs(offsets).max() > SHAPE_LIMIT_M:
        raise ValueError(f"a body shape is {NUM_JOINTS} finite offsets within {SHAPE_LIMIT_M} m, got {offsets.shape}")
    return json.dumps({"body_shape": 1, "offsets": np.round(offsets, 4).tolist(), "stature_m": round(float(stature_m), 3),
                       "legs": round(float(legs), 3), "arms": round(float(arms), 3)}, separators=(",", ":"))


def encode_clock_ping(board_ms):
    return CLOCK_PING_MSG.pack(CLOCK_PING, board_ms)


def decode_clock_pong(data):
    """A CLOCK_PONG -> (board time ms it echoes, page time ms when the page received the ping)."""
    if len(data) != CLOCK_PONG_MSG.size:
        raise ProtocolError(f"CLOCK_PONG is {len(data)} bytes, expected {CLOCK_PONG_MSG.size}")
    _, board_ms, page_ms = CLOCK_PONG_MSG.unpack(data)
    if not math.isfinite(board_ms):
        raise ProtocolError("CLOCK_PONG echoes a board time that is not finite", "value")
    check_page_time(page_ms)
    return board_ms, page_ms


def check_page_time(page_ms):
    if not math.isfinite(page_ms):
        raise ProtocolError("page time is NaN or infinite", "value")
    if not 0.0 <= page_ms <= PAGE_TIME_LIMIT_MS:
        raise ProtocolError(f"page time {page_ms:.6g} ms is outside 0..{PAGE_TIME_LIMIT_MS:.3g}", "range")


def decode_hello(text):
    """A HELLO text message -> ("code", "123456") or ("token", "..."); ProtocolError otherwise."""
    if len(text) > MAX_TEXT:
        raise ProtocolError(f"HELLO is {len(text)} characters, more than {MAX_TEXT}")
    try:
        hello = json.loads(text)
    except (ValueError, RecursionError):
        raise ProtocolError("HELLO is not JSON") from None
    if not isinstance(hello, dict):
        raise ProtocolError("HELLO is not a JSON object")
    code, token = hello.get("code"), hello.get("token")
    if isinstance(code, str) and len(code) == CODE_DIGITS and code.isascii() and code.isdigit():
        return "code", code
    if isinstance(token, str) and 16 <= len(token) <= 128 and token.isascii() and token.isalnum():
        return "token", token
    raise ProtocolError("HELLO carries neither a 6-digit code nor a token", "value")


def message_type(data):
    """The type byte of a binary message (ProtocolError when empty)."""
    if not data:
        raise ProtocolError("empty message")
    return data[0]
