"""The WebXR headset link's messages: protocol.md section 9's test vectors against the board's reference code
and against the page's own JavaScript (run in node), the decoders' refusals, and the page's forward
kinematics against edge.skeleton."""
import json
import re
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from edge import quat
from edge.skeleton import JOINT_NAMES, OFFSETS, PARENTS, fk
from firmware_bridge.samples import HeadsetSample
from firmware_bridge.wire import webxr as wire
from firmware_bridge.wire.framing import ProtocolError, cobs_decode
from firmware_bridge.wire.messages import PoseFrame, encode_headset_pose, pose_record

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "firmware_bridge" / "wire" / "protocol.md"
PAGE = ROOT / "firmware_bridge" / "transports" / "webxr_page"
S45 = np.sqrt(0.5)
FUZZ = settings(max_examples=500, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])


def doc_vectors():
    blocks = re.findall(r"```hex (\w+) message\n(.*?)```", DOC.read_text(encoding="utf-8"), flags=re.S)
    return {name: bytes.fromhex(text) for name, text in blocks}


def headset_payload():
    """The HEADSET_POSE payload of protocol.md 7.2."""
    h = HeadsetSample(t=0.0, head_pos=np.array([0.25, 1.625, -0.5]), head_rot=np.array([S45, 0.0, S45, 0.0]),
                      hand_pos=np.array([[-0.25, 1.125, 0.375], [0.0, 0.0, 0.0]]),
                      hand_rot=np.array([[1.0, 0, 0, 0], [1.0, 0, 0, 0]]), hand_valid=np.array([True, False]))
    return cobs_decode(encode_headset_pose(h, 0)[:-1])[8:-2]


def example_pose_frame():
    """The POSE_FRAME of protocol.md 7.3."""
    rot = np.tile([1.0, 0, 0, 0], (21, 1))
    rot[0], rot[14], rot[18] = [0.9659258, 0, 0.2588190, 0], [S45, S45, 0, 0], [0.9238795, 0.3826834, 0, 0]
    return PoseFrame(0.0, np.array([0.012, 0.951, -0.347]), rot, np.array([1.0, 0.0]), 10, 3, 4)


def test_vectors_in_the_doc_are_the_reference_encoders_output():
    v = doc_vectors()
    assert set(v) == {"XR_POSE", "XR_BODY", "CLOCK_PING", "CLOCK_PONG"}
    assert wire.encode_xr_pose(300, 1234.5, headset_payload()) == v["XR_POSE"]
    body = bytearray(wire.XR_BODY_SIZE)
    wire.encode_xr_body_into(body, 1000, 1234.5, pose_record(example_pose_frame()).tobytes())
    assert bytes(body) == v["XR_BODY"]
    assert wire.encode_clock_ping(5000.25) == v["CLOCK_PING"]
    assert wire.decode_clock_pong(v["CLOCK_PONG"]) == (5000.25, 1240.75)
    seq, page_ms, sample = wire.decode_xr_pose(v["XR_POSE"])
    assert (seq, page_ms, sample.t) == (300, 1234.5, 1.2345)
    np.testing.assert_allclose(sample.head_pos, [0.25, 1.625, -0.5])
    np.testing.assert_allclose(sample.head_rot, [S45, 0, S45, 0], atol=1e-4)
    assert list(sample.hand_valid) == [True, False]


@pytest.mark.parametrize("change, kind", [
    (lambda m: m[:-1], "framing"),                                          # a byte short
    (lambda m: m + b"\x00", "framing"),                                     # a byte long
    (lambda m: m[:1] + b"\x01" + m[2:], "value"),                           # reserved flags
    (lambda m: m[:4] + struct.pack("<d", float("nan")) + m[12:], "value"),  # NaN time
    (lambda m: m[:4] + struct.pack("<d", -1.0) + m[12:], "range"),          # a time before the page loaded
    (lambda m: m[:4] + struct.pack("<d", 1e300) + m[12:], "range"),
    (lambda m: m[:12] + struct.pack("<f", 31.0) + m[16:], "range"),         # head 31 m from the origin
    (lambda m: m[:12] + struct.pack("<f", float("inf")) + m[16:], "value"),
    (lambda m: m[:24] + b"\x00" * 8 + m[32:], "quaternion"),                # not a rotation
])
def test_xr_pose_decoder_refuses_with_a_kind(change, kind):
    message = change(doc_vectors()["XR_POSE"])
    with pytest.raises(ProtocolError) as refused:
        wire.decode_xr_pose(message)
    assert refused.value.kind == kind


@pytest.mark.parametrize("text, ok", [
    ('{"code": "123456"}', True), ('{"token": "0123456789abcdef0123456789abcdef"}', True),
    ('{"code": "12345"}', False), ('{"code": 123456}', False), ('{"code": "12345a"}', False),
    ('{"code": "١٢٣٤٥٦"}', False),                      # digits, but not ASCII ones
    ('{"token": "short"}', False), ('{"token": "../../etc/passwd/../../.."}', False), ("[1, 2]", False),
    ("not json", False), ("[" * 200, False), ('{"code": "123456", "pad": "' + "x" * 300 + '"}', False),
])
def test_hello(text, ok):
    if ok:
        assert wire.decode_hello(text)[0] in ("code", "token")
    else:
        with pytest.raises(ProtocolError):
            wire.decode_hello(text)


@FUZZ
@given(st.binary(max_size=300))
def test_decoders_raise_only_protocol_errors(data):
    for decode in (wire.decode_xr_pose, wire.decode_clock_pong, wire.message_type):
        try:
            decode(data)
        except ProtocolError:
            pass


# --- the page's JavaScript, run in node -------------------------------------------------------------

def run_node(script):
    node = shutil.which("node")
    if node is None:
        pytest.skip("needs node to run the page's modules (apt-get install nodejs)")
    out = subprocess.run([node, "--input-type=module", "-e", script], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_the_pages_encoder_writes_the_doc_vector():
    # The doc's head in WebXR terms: (x, y, z, w) = (0, -S45, 0, S45), which the page turns into +Y 90 deg.
    got = run_node(f"""
import {{ encodeXrPose, encodeClockPong }} from "{(PAGE / 'wire.js').as_uri()}";
const v = new DataView(new ArrayBuffer(74));
const s = Math.SQRT1_2;
encodeXrPose(v, 300, 1234.5, {{ position: {{ x: 0.25, y: 1.625, z: -0.5 }}, orientation: {{ x: 0, y: -s, z: 0, w: s }} }},
             {{ position: {{ x: -0.25, y: 1.125, z: 0.375 }}, orientation: {{ x: 0, y: -1, z: 0, w: 0 }} }}, null);
const p = new DataView(new ArrayBuffer(17));
encodeClockPong(p, 5000.25, 1240.75);
console.log(JSON.stringify([Array.from(new Uint8Array(v.buffer)), Array.from(new Uint8Array(p.buffer))]));
""")
    v = doc_vectors()
    assert bytes(got[0]) == v["XR_POSE"]           # the identity grip is (0, -1, 0, 0) in WebXR: half a turn
    assert bytes(got[1]) == v["CLOCK_PONG"]


def test_the_pages_decoder_and_skeleton_match_the_board():
    rng = np.random.default_rng(3)
    frame = example_pose_frame()
    frame.rotations = quat.normalize(rng.normal(size=(21, 4)))
    body = bytearray(wire.XR_BODY_SIZE)
    wire.encode_xr_body_into(body, 7, 99.0, pose_record(frame).tobytes())
    got = run_node(f"""
import {{ decodeXrBody, newBody }} from "{(PAGE / 'wire.js').as_uri()}";
import {{ forwardKinematics, JOINT_NAMES, PARENTS, OFFSETS }} from "{(PAGE / 'skeleton.js').as_uri()}";
const bytes = new Uint8Array({list(body)});
const body = newBody();
const ok = decodeXrBody(new DataView(bytes.buffer), body);
const positions = new Float64Array(63), scratch = new Float64Array(84);
forwardKinematics(body.rotations, body.root, positions, scratch);
console.log(JSON.stringify({{ ok, seq: body.seq, inputMs: body.inputMs, samples: body.samples, positions: Array.from(positions),
                             names: JOINT_NAMES, parents: PARENTS, offsets: OFFSETS }}));
""")
    assert got["ok"] and got["seq"] == 7 and got["inputMs"] == 99.0 and got["samples"] == 10
    assert got["names"] == list(JOINT_NAMES) and got["parents"] == [int(p) for p in PARENTS]
    np.testing.assert_allclose(got["offsets"], OFFSETS, atol=1e-12)
    _, expected = fk(quat.to_matrix(frame.rotations), np.round(frame.root_pos * 1000) / 1000)
    np.testing.assert_allclose(np.reshape(got["positions"], (21, 3)), expected, atol=2e-4)   # Q14 on the wire


def test_the_page_turns_webxr_orientations_into_edgeposes():
    """Any WebXR orientation: the board decodes q_webxr * (0, 0, 1, 0), to Q14's resolution."""
    rng = np.random.default_rng(5)
    xr = quat.normalize(rng.normal(size=(3, 4)))          # (w, x, y, z): head, left grip, right grip
    pos = rng.uniform(-2, 2, size=(3, 3))
    f = lambda v: repr(float(v))
    js = lambda k: (f"{{ position: {{ x: {f(pos[k, 0])}, y: {f(pos[k, 1])}, z: {f(pos[k, 2])} }}, orientation: "
                    f"{{ w: {f(xr[k, 0])}, x: {f(xr[k, 1])}, y: {f(xr[k, 2])}, z: {f(xr[k, 3])} }} }}")
    got = run_node(f"""
import {{ encodeXrPose }} from "{(PAGE / 'wire.js').as_uri()}";
const v = new DataView(new ArrayBuffer(74));
encodeXrPose(v, 1, 2.0, {js(0)}, {js(1)}, {js(2)});
console.log(JSON.stringify(Array.from(new Uint8Array(v.buffer))));
""")
    _, _, sample = wire.decode_xr_pose(bytes(got))
    turned = quat.mul(xr, np.array([0.0, 0.0, 1.0, 0.0]))
    for decoded, expected in zip([sample.head_rot, *sample.hand_rot], turned, strict=True):
        sign = np.sign(np.dot(decoded, expected))
        np.testing.assert_allclose(sign * decoded, expected, atol=1e-4)
    np.testing.assert_allclose(np.vstack([sample.head_pos, sample.hand_pos]), pos, atol=1e-6)


def test_the_page_draws_the_users_own_body_from_the_shape_the_board_sends():
    """BODY_SHAPE's offsets (the user's legs and arms at their size) are the bones the page's FK hangs
    each XR_BODY on: the page's joints are the board's FK on the same offsets, not the canonical body's."""
    from edge.proportions import UserBody
    rng = np.random.default_rng(4)
    frame = example_pose_frame()
    frame.rotations = quat.normalize(rng.normal(size=(21, 4)))
    body = bytearray(wire.XR_BODY_SIZE)
    wire.encode_xr_body_into(body, 9, 5.0, pose_record(frame).tobytes())
    user = UserBody(1.08, 0.93)
    offsets = user.offsets / 1.1                             # a user 1.1x shorter than the canonical body
    text = wire.encode_body_shape(offsets, 1.62, user.legs, user.arms)
    got = run_node(f"""
import {{ decodeXrBody, describeShape, newBody, readBodyShape }} from "{(PAGE / 'wire.js').as_uri()}";
import {{ forwardKinematics }} from "{(PAGE / 'skeleton.js').as_uri()}";
const bytes = new Uint8Array({list(body)});
const body = newBody();
decodeXrBody(new DataView(bytes.buffer), body);
const shape = readBodyShape(JSON.parse({json.dumps(text)}));
const positions = new Float64Array(63), scratch = new Float64Array(84);
forwardKinematics(body.rotations, body.root, positions, scratch, shape.offsets);
console.log(JSON.stringify({{ positions: Array.from(positions), text: describeShape(shape),
                             canonical: describeShape(readBodyShape({{ ...JSON.parse({json.dumps(text)}), legs: 1, arms: 1 }})) }}));
""")
    root = np.round(frame.root_pos * 1000) / 1000
    _, expected = fk(quat.to_matrix(frame.rotations), root, offsets=offsets)
    np.testing.assert_allclose(np.reshape(got["positions"], (21, 3)), expected, atol=2e-4)   # Q14, offsets to 0.1 mm
    _, canonical = fk(quat.to_matrix(frame.rotations), root)
    assert np.abs(canonical - expected).max() > 0.05                # the shape matters by centimetres
    assert got["text"] == "1.62 m legs 1.08x arms 0.93x" and got["canonical"] == "1.62 m"


@pytest.mark.parametrize("change", [
    {"body_shape": 2}, {"offsets": "x"}, {"offsets": [[0, 0, 0]] * 20}, {"offsets": [[0, 0]] + [[0, 0, 0]] * 20},
    {"offsets": [[0, 0, 1.5]] + [[0, 0, 0]] * 20}, {"offsets": [[0, 0, "1"]] + [[0, 0, 0]] * 20},
    {"stature_m": 0.2}, {"stature_m": None}, {"legs": 3}, {"arms": "1"}])
def test_the_page_keeps_its_body_when_a_shape_is_not_one(change):
    good = json.loads(wire.encode_body_shape(OFFSETS, 1.75))
    got = run_node(f"""
import {{ readBodyShape }} from "{(PAGE / 'wire.js').as_uri()}";
console.log(JSON.stringify([readBodyShape({json.dumps(good)}) !== null, readBodyShape({json.dumps({**good, **change})})]));
""")
    assert got == [True, None]


def test_the_board_refuses_to_describe_a_body_no_one_has():
    for bad in (np.zeros((20, 3)), np.full((21, 3), np.nan), np.full((21, 3), 1.5)):
        with pytest.raises(ValueError, match="body shape"):
            wire.encode_body_shape(bad, 1.75)
