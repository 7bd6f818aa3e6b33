"""Minimal OSC 1.0 encoding (and a decoder for tests): messages, bundles, and fixed-layout packets.

OSC 1.0 in brief (opensoundcontrol.org, spec 1.0):
- every item is big-endian and padded with zero bytes to a multiple of 4;
- a string is its bytes, at least one NUL, then NULs up to the next multiple of 4;
- a message is: address string, type-tag string (',' then one tag per argument), arguments;
- int32 'i', float32 'f' and string 's' are the only types we send;
- a bundle is: the string '#bundle', a 64-bit time tag, then elements, each an int32 size and a
  message (or a nested bundle). Time tag 1 means "immediately".

`PacketTemplate` encodes a packet once and rewrites only its float arguments in place every frame,
so a sender allocates nothing per frame for the wire format.
"""
import struct

import numpy as np

BUNDLE_TAG = b"#bundle\0"
IMMEDIATELY = 1          # the OSC time tag meaning "apply on receipt"


class OscError(ValueError):
    """A packet that cannot be decoded; the message says what is wrong."""


# Encoding ----------------------------------------------------------------------------------------

def pad4(size):
    """The size rounded up to the next multiple of 4."""
    return (size + 3) & ~3


def encode_string(text):
    """An OSC string: UTF-8 bytes, then 1 to 4 NULs so the length is a multiple of 4."""
    raw = text.encode("utf-8")
    if b"\0" in raw:
        raise ValueError(f"OSC strings cannot contain NUL: {text!r}")
    return raw + b"\0" * (pad4(len(raw) + 1) - len(raw))


def type_tag(value):
    """The OSC type tag of one argument: 's', 'f' or 'i'."""
    if isinstance(value, str):
        return "s"
    # bool is an int in Python; OSC 1.0 has no boolean, so refuse it rather than guess.
    if isinstance(value, (bool, np.bool_)):
        raise TypeError("OSC 1.0 has no boolean: send an int 0 or 1")
    if isinstance(value, (int, np.integer)):
        return "i"
    if isinstance(value, (float, np.floating)):
        return "f"
    raise TypeError(f"cannot send {type(value).__name__} over OSC (use str, int or float)")


def encode_argument(value):
    tag = type_tag(value)
    if tag == "s":
        return encode_string(value)
    if tag == "i":
        return struct.pack(">i", int(value))
    return struct.pack(">f", float(value))


def encode_message(address, *args):
    """One OSC message: encode_message('/VMC/Ext/OK', 1)."""
    if not address.startswith("/"):
        raise ValueError(f"OSC addresses start with '/': {address!r}")
    tags = "," + "".join(type_tag(a) for a in args)
    return encode_string(address) + encode_string(tags) + b"".join(encode_argument(a) for a in args)


def encode_bundle(elements, timetag=IMMEDIATELY):
    """A bundle of already encoded messages (or bundles), each prefixed with its int32 size."""
    parts = [BUNDLE_TAG, struct.pack(">Q", timetag)]
    for element in elements:
        parts.append(struct.pack(">i", len(element)))
        parts.append(element)
    return b"".join(parts)


# Decoding (tests, and tools that listen to our own output) ------------------------------------------

def decode_string(data, offset):
    """(text, offset after the padded string)."""
    end = data.find(b"\0", offset)
    if end < 0:
        raise OscError(f"string at byte {offset} has no NUL terminator")
    return data[offset:end].decode("utf-8"), pad4(end + 1)


def decode_message(data):
    """(address, [arguments]) of one message; floats come back as Python floats (float32 values)."""
    data = bytes(data)
    if len(data) % 4:
        raise OscError(f"packet size {len(data)} is not a multiple of 4")
    address, offset = decode_string(data, 0)
    if not address.startswith("/"):
        raise OscError(f"address {address!r} does not start with '/'")
    tags, offset = decode_string(data, offset)
    if not tags.startswith(","):
        raise OscError(f"type tags {tags!r} do not start with ','")
    args = []
    for tag in tags[1:]:
        if tag == "s":
            value, offset = decode_string(data, offset)
        elif tag in "if":
            if offset + 4 > len(data):
                raise OscError(f"message {address} ends inside its arguments")
            value = struct.unpack_from(">i" if tag == "i" else ">f", data, offset)[0]
            offset += 4
        else:
            raise OscError(f"unsupported type tag {tag!r} in {address}")
        args.append(value)
    if offset != len(data):
        raise OscError(f"message {address} has {len(data) - offset} bytes after its arguments")
    return address, args


def decode_bundle(data):
    """(time tag, [element bytes]) of one bundle."""
    data = bytes(data)
    if not data.startswith(BUNDLE_TAG) or len(data) < 16:
        raise OscError("not an OSC bundle")
    timetag = struct.unpack_from(">Q", data, 8)[0]
    elements, offset = [], 16
    while offset < len(data):
        if offset + 4 > len(data):
            raise OscError(f"bundle element size at byte {offset} is cut off")
        size = struct.unpack_from(">i", data, offset)[0]
        offset += 4
        if size < 0 or size % 4 or offset + size > len(data):
            raise OscError(f"bundle element at byte {offset} has a bad size {size}")
        elements.append(data[offset:offset + size])
        offset += size
    return timetag, elements


def decode_packet(data):
    """Every message in a packet as (address, args), bundles flattened in order."""
    data = bytes(data)
    if data.startswith(BUNDLE_TAG):
        _, elements = decode_bundle(data)
        return [message for element in elements for message in decode_packet(element)]
    return [decode_message(data)]


# Fixed-layout packets --------------------------------------------------------------------------

def float_offsets(address, args):
    """Byte offsets, inside the encoded message, of its float arguments."""
    offset = len(encode_string(address)) + len(encode_string("," + "".join(type_tag(a) for a in args)))
    offsets = []
    for arg in args:
        if type_tag(arg) == "f":
            offsets.append(offset)
        offset += len(encode_argument(arg))
    return offsets


class PacketTemplate:
    """A message, or a bundle of messages, encoded once; only its float arguments change.

    Strings and ints (bone names, flags) are fixed at construction. `set_floats(values)` writes the
    floats, in the order they appear in the packet, straight into `buffer`, which is what goes on
    the wire. Every OSC item is 4-byte aligned, so each float is one slot of a big-endian float32
    view of the buffer.
    """

    def __init__(self, messages, bundle=True, timetag=IMMEDIATELY):
        """messages: [(address, args)], args with placeholder floats (their type is what counts)."""
        if not bundle and len(messages) != 1:
            raise ValueError("a packet that is not a bundle holds exactly one message")
        encoded = [encode_message(address, *args) for address, args in messages]
        offsets = []
        start = len(BUNDLE_TAG) + 8 if bundle else 0
        for (address, args), message in zip(messages, encoded, strict=True):
            if bundle:
                start += 4                                   # the element's size prefix
            offsets += [start + o for o in float_offsets(address, args)]
            start += len(message)
        self.buffer = bytearray(encode_bundle(encoded, timetag) if bundle else encoded[0])
        self._slots = np.array(offsets, dtype=np.intp) // 4
        self._floats = np.frombuffer(self.buffer, dtype=">f4")
        self.float_count = len(offsets)

    def set_floats(self, values):
        """Write all float arguments (len == float_count), converted to big-endian float32."""
        self._floats[self._slots] = values
