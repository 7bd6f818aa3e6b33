"""Pose outputs: OSC wire format, VMC and VRChat over real UDP on 127.0.0.1, BVH recordings that
an independent reader (the `bvh` package on PyPI) and motion.bvh both load back."""
import socket
import struct

import numpy as np
import pytest

from motion import bvh as edge_bvh
from edge import quat
from edge.frame import Pose
from edge.signals import EYE_OFFSET
from edge.skeleton import HEAD, JOINT, JOINT_NAMES, NUM_JOINTS, OFFSETS, PARENTS, fk
from firmware_bridge.outputs import to_unity_matrix, to_unity_position, to_unity_quaternion
from firmware_bridge.outputs import osc
from firmware_bridge.outputs.bvh_writer import BvhWriter, zxy_euler_degrees
from firmware_bridge.outputs.vmc import BONE_NAMES, VmcSender
from firmware_bridge.outputs.vrchat import VrchatSender, unity_euler_degrees

LOOPBACK = "127.0.0.1"
MIRROR = np.diag([-1.0, 1.0, 1.0])
FLOAT32_TOL = 1e-6


# Helpers ---------------------------------------------------------------------------------------

def rx(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rz(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


AXIS_ROTATION = {"X": rx, "Y": ry, "Z": rz}


def random_rotations(rng, n, max_angle=np.pi):
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    return quat.to_matrix(quat.from_axis_angle(axes, rng.uniform(-max_angle, max_angle, n)))


def rest_pose(root=(0.0, 0.95, 0.0)):
    rotations = np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3)).copy()
    return pose_from_local(rotations, np.array(root))


def pose_from_local(rotations, root, frame=0):
    _, positions = fk(rotations, root)
    return Pose(frame=frame, positions=positions, rotations=rotations)


def synthetic_motion(frames=12, seed=0):
    """Random small local rotations, a root that turns about Y through large angles and drifts."""
    rng = np.random.default_rng(seed)
    poses = []
    for t in range(frames):
        local = random_rotations(rng, NUM_JOINTS, max_angle=0.6)
        local[0] = ry(-170 + 30 * t) @ local[0]
        root = np.array([0.3 * np.sin(t / 3), 0.95 + 0.02 * np.cos(t), 0.05 * t])
        poses.append(pose_from_local(local, root, frame=t))
    return poses


@pytest.fixture
def receiver():
    """A UDP socket on 127.0.0.1 and an ephemeral port."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((LOOPBACK, 0))
    sock.settimeout(2.0)
    yield sock
    sock.close()


def receive(sock, datagrams):
    return [sock.recv(65536) for _ in range(datagrams)]


# OSC -------------------------------------------------------------------------------------------

def test_osc_strings_end_with_one_to_four_nuls_on_a_4_byte_boundary():
    assert osc.encode_string("") == b"\0\0\0\0"
    assert osc.encode_string("abc") == b"abc\0"
    assert osc.encode_string("abcd") == b"abcd\0\0\0\0"
    assert osc.encode_string("root") == b"root\0\0\0\0"


def test_osc_messages_match_the_spec_examples_byte_for_byte():
    # The two examples of the OSC 1.0 specification.
    assert osc.encode_message("/oscillator/4/frequency", 440.0) == (
        b"/oscillator/4/frequency\0" b",f\0\0" + bytes.fromhex("43dc0000"))
    assert osc.encode_message("/foo", 1000, -1, "hello", 1.234, 5.678) == (
        b"/foo\0\0\0\0" b",iisff\0\0" + bytes.fromhex("000003e8 ffffffff") + b"hello\0\0\0"
        + bytes.fromhex("3f9df3b6 40b5b22d"))


def test_osc_message_round_trips_strings_ints_and_float32():
    data = osc.encode_message("/VMC/Ext/Bone/Pos", "LeftUpperArm", 0.1, -2.5, 3, np.float32(0.25), np.int64(7))
    assert len(data) % 4 == 0
    address, args = osc.decode_message(data)
    assert address == "/VMC/Ext/Bone/Pos"
    assert args[0] == "LeftUpperArm" and args[3] == 3 and args[5] == 7
    assert args[1] == pytest.approx(0.1, abs=FLOAT32_TOL) and args[2] == -2.5 and args[4] == 0.25


def test_osc_bundle_is_tagged_immediate_and_decodes_to_its_messages_in_order():
    messages = [osc.encode_message("/a", 1.0), osc.encode_message("/bb", "x", 2)]
    data = osc.encode_bundle(messages)
    assert data[:8] == b"#bundle\0" and struct.unpack(">Q", data[8:16])[0] == osc.IMMEDIATELY
    assert struct.unpack(">i", data[16:20])[0] == len(messages[0])
    timetag, elements = osc.decode_bundle(data)
    assert timetag == 1 and elements == messages
    assert osc.decode_packet(data) == [("/a", [1.0]), ("/bb", ["x", 2])]


def test_osc_refuses_types_it_cannot_send():
    with pytest.raises(TypeError, match="boolean"):
        osc.encode_message("/x", True)
    with pytest.raises(TypeError, match="list"):
        osc.encode_message("/x", [1.0])
    with pytest.raises(ValueError, match="start with '/'"):
        osc.encode_message("x", 1)


def test_osc_decoder_rejects_cut_or_malformed_packets():
    good = osc.encode_message("/a", 1.0, 2.0)
    with pytest.raises(osc.OscError):
        osc.decode_message(good[:-4])                      # one float short
    with pytest.raises(osc.OscError):
        osc.decode_message(good[:-2])                      # not a multiple of 4
    with pytest.raises(osc.OscError):
        osc.decode_bundle(osc.encode_bundle([good])[:-4])  # element size larger than what is left


def test_packet_template_rewrites_only_the_floats_in_place():
    messages = [("/a", ("name", 0.0, 0.0)), ("/b", (1,)), ("/c", (0.0,))]
    template = osc.PacketTemplate(messages)
    assert template.float_count == 3
    buffer = template.buffer
    template.set_floats([1.5, -2.0, 3.25])
    assert template.buffer is buffer                       # no new buffer per frame
    assert bytes(buffer) == osc.encode_bundle([osc.encode_message("/a", "name", 1.5, -2.0),
                                               osc.encode_message("/b", 1), osc.encode_message("/c", 3.25)])
    single = osc.PacketTemplate([("/p", (0.0, 0.0, 0.0))], bundle=False)
    single.set_floats(np.array([1.0, 2.0, 3.0]))
    assert osc.decode_message(single.buffer) == ("/p", [1.0, 2.0, 3.0])


# Unity's frame ---------------------------------------------------------------------------------

def test_unity_quaternion_is_the_rotation_mirrored_across_x():
    m = random_rotations(np.random.default_rng(1), 50)
    q = to_unity_quaternion(m)                               # (x, y, z, w)
    as_matrix = quat.to_matrix(q[:, [3, 0, 1, 2]])
    assert np.allclose(as_matrix, MIRROR @ m @ MIRROR, atol=1e-12)
    assert np.allclose(to_unity_matrix(m), MIRROR @ m @ MIRROR)
    # Mirroring commutes with rotating: rotate-then-mirror == mirror-then-rotate-in-Unity.
    v = np.array([0.3, -0.2, 0.9])
    assert np.allclose(to_unity_matrix(m) @ to_unity_position(v), to_unity_position(m @ v))


# VMC -------------------------------------------------------------------------------------------

def test_vmc_frame_is_one_bundle_of_root_then_all_bones_then_ok_and_time(receiver):
    pose = synthetic_motion(1)[0]
    with VmcSender(LOOPBACK, receiver.getsockname()[1], mode="bundle") as vmc:
        vmc.send(pose, t=1.25)
    (datagram,) = receive(receiver, 1)
    assert datagram.startswith(b"#bundle\0")
    messages = osc.decode_packet(datagram)
    addresses = [a for a, _ in messages]
    assert addresses == ["/VMC/Ext/Root/Pos"] + ["/VMC/Ext/Bone/Pos"] * NUM_JOINTS + ["/VMC/Ext/OK", "/VMC/Ext/T"]
    assert messages[0][1] == ["root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    bones = {args[0]: np.array(args[1:]) for address, args in messages[1:-2]}
    assert list(bones) == list(BONE_NAMES)
    assert BONE_NAMES[:5] == ("Hips", "Spine", "Chest", "Neck", "Head")
    assert {"LeftShoulder", "LeftUpperArm", "LeftLowerArm", "LeftHand", "RightHand",
            "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "LeftToes", "RightToes"} <= set(bones)
    assert messages[-2][1] == [1] and messages[-1][1] == [1.25]
    # Hips carry the world pelvis position, the others their local offsets; X is mirrored.
    hips = bones["Hips"]
    assert np.allclose(hips[:3], pose.positions[0] * [-1, 1, 1], atol=FLOAT32_TOL)
    knee = bones["LeftLowerLeg"]
    assert np.allclose(knee[:3], OFFSETS[JOINT["l_knee"]] * [-1, 1, 1], atol=FLOAT32_TOL)
    assert np.allclose(bones["LeftUpperLeg"][:3], [-0.09, -0.06, 0.0], atol=FLOAT32_TOL)  # left is -X in Unity
    # Every bone's rotation is its local rotation mirrored (quaternions up to sign).
    for j, name in enumerate(BONE_NAMES):
        q = bones[name][3:][[3, 0, 1, 2]]
        assert np.allclose(quat.to_matrix(q), MIRROR @ pose.rotations[j] @ MIRROR, atol=1e-5), name


def test_vmc_left_arm_swung_forward_is_unity_yaw_plus_90(receiver):
    # Here: the left arm (rest along +X) turned to +Z is a rotation of -90 degrees about +Y.
    rotations = np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3)).copy()
    rotations[JOINT["l_shoulder"]] = ry(-90)
    pose = pose_from_local(rotations, np.array([0.0, 0.95, 0.0]))
    assert np.allclose(pose.positions[JOINT["l_elbow"]] - pose.positions[JOINT["l_shoulder"]], [0, 0, 0.28])
    with VmcSender(LOOPBACK, receiver.getsockname()[1]) as vmc:
        vmc.send(pose)
    bones = {args[0]: args[1:] for _, args in osc.decode_packet(receive(receiver, 1)[0])[1:-2]}
    # In Unity the same motion is Quaternion.Euler(0, 90, 0) = (x, y, z, w) = (0, 0.7071, 0, 0.7071):
    x, y, z, w = bones["LeftUpperArm"][3:]
    s = np.sqrt(0.5)
    assert np.allclose([x, y, z, w], [0, s, 0, s], atol=FLOAT32_TOL)
    # ... which takes Unity's left (-1, 0, 0) to forward (0, 0, 1).
    assert np.allclose(quat.rotate(np.array([w, x, y, z]), np.array([-1.0, 0, 0])), [0, 0, 1], atol=1e-6)
    assert np.allclose(bones["RightUpperArm"][3:], [0, 0, 0, 1])


def test_vmc_unbundled_sends_the_same_messages_one_datagram_each(receiver):
    pose = synthetic_motion(1, seed=3)[0]
    with VmcSender(LOOPBACK, receiver.getsockname()[1], mode="bundle") as vmc:
        vmc.send(pose, t=0.5)
    bundled = osc.decode_packet(receive(receiver, 1)[0])
    with VmcSender(LOOPBACK, receiver.getsockname()[1], mode="messages") as vmc:
        vmc.send(pose, t=0.5)
    datagrams = receive(receiver, NUM_JOINTS + 3)
    assert not any(d.startswith(b"#bundle") for d in datagrams)
    assert [osc.decode_message(d) for d in datagrams] == bundled


def test_vmc_keeps_sending_when_nobody_listens():
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind((LOOPBACK, 0))
    port = probe.getsockname()[1]
    probe.close()                                          # now nothing listens on that port
    with VmcSender(LOOPBACK, port) as vmc:
        for pose in synthetic_motion(3):
            vmc.send(pose)
    assert vmc.stats["frames"] == 3


# VRChat ----------------------------------------------------------------------------------------

def test_unity_euler_angles_rebuild_the_rotation_as_ry_rx_rz():
    m = random_rotations(np.random.default_rng(2), 200)
    gimbal = np.stack([ry(30) @ rx(90) @ rz(20), ry(-50) @ rx(-90) @ rz(10)])
    for r in np.concatenate([m, gimbal]):
        x, y, z = unity_euler_degrees(r)
        assert np.allclose(ry(y) @ rx(x) @ rz(z), r, atol=1e-9)
    assert np.allclose(unity_euler_degrees(ry(90) @ rx(20) @ rz(-30)), [20, 90, -30])


def test_vrchat_sends_position_and_rotation_for_each_tracker_then_the_head(receiver):
    pose = synthetic_motion(1, seed=5)[0]
    with VrchatSender(LOOPBACK, receiver.getsockname()[1]) as vrchat:
        vrchat.send(pose)
    messages = [osc.decode_message(d) for d in receive(receiver, 14)]
    expected = [f"/tracking/trackers/{i}/{what}" for i in ("1", "2", "3", "4", "5", "6", "head")
                for what in ("position", "rotation")]
    assert [a for a, _ in messages] == expected
    values = {a: np.array(v) for a, v in messages}
    world_rot, _ = fk(pose.rotations, pose.positions[0])
    for k, joint in enumerate(("pelvis", "chest", "l_ankle", "r_ankle", "l_knee", "r_knee"), start=1):
        j = JOINT[joint]
        assert np.allclose(values[f"/tracking/trackers/{k}/position"], pose.positions[j] * [-1, 1, 1], atol=FLOAT32_TOL)
        x, y, z = values[f"/tracking/trackers/{k}/rotation"]
        assert np.allclose(ry(y) @ rx(x) @ rz(z), MIRROR @ world_rot[j] @ MIRROR, atol=1e-5)
    eyes = pose.positions[HEAD] + world_rot[HEAD] @ EYE_OFFSET
    assert np.allclose(values["/tracking/trackers/head/position"], eyes * [-1, 1, 1], atol=FLOAT32_TOL)


def test_vrchat_hips_turned_to_their_left_is_a_negative_unity_yaw(receiver):
    # Here +30 degrees about +Y turns the body from +Z toward +X, its left. Unity's left is -X,
    # so Unity sees a yaw of -30 degrees: rotation (0, -30, 0).
    rotations = np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3)).copy()
    rotations[0] = ry(30)
    pose = pose_from_local(rotations, np.array([0.2, 0.95, -0.1]))
    with VrchatSender(LOOPBACK, receiver.getsockname()[1], trackers=("pelvis",), send_head=False) as vrchat:
        vrchat.send(pose)
    (position, rotation) = [osc.decode_message(d) for d in receive(receiver, 2)]
    assert position == ("/tracking/trackers/1/position", pytest.approx([-0.2, 0.95, -0.1], abs=FLOAT32_TOL))
    assert rotation == ("/tracking/trackers/1/rotation", pytest.approx([0.0, -30.0, 0.0], abs=1e-4))


def test_vrchat_refuses_more_than_eight_trackers_or_unknown_joints():
    with pytest.raises(ValueError, match="1..8"):
        VrchatSender(trackers=JOINT_NAMES[:9])
    with pytest.raises(ValueError, match="unknown joint"):
        VrchatSender(trackers=("pelvis", "left_foot"))


# BVH -------------------------------------------------------------------------------------------

def test_zxy_euler_angles_rebuild_the_rotation_as_rz_rx_ry():
    m = random_rotations(np.random.default_rng(4), 200)
    gimbal = np.stack([rz(40) @ rx(90) @ ry(15), rz(-20) @ rx(-90) @ ry(70)])
    for r in np.concatenate([m, gimbal]):
        z, x, y = zxy_euler_degrees(r)
        assert np.allclose(rz(z) @ rx(x) @ ry(y), r, atol=1e-9)
    assert np.allclose(zxy_euler_degrees(rz(10) @ rx(-20) @ ry(30)), [10, -20, 30])


def write_bvh(path, poses, fps=60.0):
    with BvhWriter(path, fps=fps) as writer:
        for pose in poses:
            writer.send(pose)
    return writer


def bvh_package_world_positions(mocap):
    """FK over what the `bvh` package parsed, with rotation matrices built here: [T,J,3] in file units."""
    names = mocap.get_joints_names()
    index = {name: k for k, name in enumerate(names)}
    positions = np.zeros((mocap.nframes, len(names), 3))
    for t in range(mocap.nframes):
        world_rot = [None] * len(names)
        for k, name in enumerate(names):
            channels = mocap.joint_channels(name)
            values = dict(zip(channels, mocap.frame_joint_channels(t, name, channels), strict=True))
            local = np.eye(3)
            for channel in channels:
                if channel.endswith("rotation"):
                    local = local @ AXIS_ROTATION[channel[0]](values[channel])
            parent = mocap.joint_parent(name)
            if parent is None:
                positions[t, k] = [values["Xposition"], values["Yposition"], values["Zposition"]]
                world_rot[k] = local
            else:
                p = index[parent.name]
                positions[t, k] = positions[t, p] + world_rot[p] @ np.array(mocap.joint_offset(name))
                world_rot[k] = world_rot[p] @ local
    return names, positions


def test_bvh_loads_in_the_independent_bvh_package_with_all_joints_frames_and_positions(tmp_path):
    bvh = pytest.importorskip("bvh", reason="needs the `bvh` package from PyPI (test dependency)")
    poses = synthetic_motion(12)
    path = tmp_path / "take.bvh"
    write_bvh(path, poses, fps=60)
    mocap = bvh.Bvh(path.read_text())
    assert len(mocap.get_joints()) == NUM_JOINTS
    assert mocap.get_joints_names() == list(JOINT_NAMES)
    assert mocap.nframes == len(poses) and len(mocap.frames) == len(poses)
    assert mocap.frame_time == pytest.approx(1 / 60)
    assert mocap.joint_channels("pelvis") == ["Xposition", "Yposition", "Zposition",
                                              "Zrotation", "Xrotation", "Yrotation"]
    assert mocap.joint_channels("l_knee") == ["Zrotation", "Xrotation", "Yrotation"]
    assert mocap.joint_offset("l_knee") == pytest.approx((0.0, -43.0, 0.0))
    assert mocap.joint_parent_index("l_hip") == JOINT["pelvis"]
    assert len(mocap.search("End", "Site")) == 5                # head, both wrists, both toes
    names, positions_cm = bvh_package_world_positions(mocap)
    expected = np.stack([p.positions for p in poses])
    assert np.allclose(positions_cm / 100.0, expected[:, [JOINT[n] for n in names]], atol=1e-4)


def test_bvh_reloads_with_edge_bvh_to_the_input_joint_positions(tmp_path):
    poses = synthetic_motion(12, seed=7)
    path = tmp_path / "take.bvh"
    write_bvh(path, poses, fps=30)
    clip = edge_bvh.load(path)
    assert clip.frames == len(poses) and clip.fps == pytest.approx(30, rel=1e-6)
    assert [clip.names[k] for k in range(len(clip.names)) if not clip.names[k].endswith("_end")] == list(JOINT_NAMES)
    assert [clip.parents[clip.index(n)] for n in JOINT_NAMES[1:]] == [clip.index(JOINT_NAMES[p]) for p in PARENTS[1:]]
    _, world = clip.world()
    got = world[:, [clip.index(n) for n in JOINT_NAMES]] / 100.0
    assert np.abs(got - np.stack([p.positions for p in poses])).max() < 1e-4


def test_bvh_frame_count_is_right_after_flush_and_after_close(tmp_path):
    path = tmp_path / "stream.bvh"
    poses = synthetic_motion(5)
    writer = BvhWriter(path)
    for pose in poses[:2]:
        writer.send(pose)
    writer.flush()
    assert edge_bvh.load(path).frames == 2          # a reader mid-take sees a valid file
    for pose in poses[2:]:
        writer.send(pose)
    writer.close()
    writer.close()                                  # closing twice is harmless
    assert edge_bvh.load(path).frames == 5
    assert "Frames: 5 " in path.read_text()


def test_vmc_split_mode_sends_the_same_frame_in_bundles_that_fit_one_ethernet_frame(receiver):
    """The default: every datagram at most 1,472 bytes (no IP fragments on a LAN), the frame's messages
    in order across them, the same values as the single bundle."""
    pose = synthetic_motion(1)[0]
    with VmcSender(LOOPBACK, receiver.getsockname()[1]) as vmc, \
            VmcSender(LOOPBACK, receiver.getsockname()[1], mode="bundle") as whole:
        vmc.send(pose, t=1.25)
        split = receive(receiver, len(vmc._packets))
        whole.send(pose, t=1.25)
        (one,) = receive(receiver, 1)
    assert len(split) == 2 and max(len(d) for d in split) <= 1472 < len(one)
    assert all(d.startswith(b"#bundle\0") for d in split)
    assert [m for d in split for m in osc.decode_packet(d)] == osc.decode_packet(one)


def test_every_output_carries_the_calibrated_body_size(receiver, tmp_path):
    """scale (1 / height_scale): VMC's Hips and bone offsets, VRChat's positions and BVH's offsets and
    root are the user's size, not the canonical 1.75 m body's."""
    from firmware_bridge.outputs.bvh_writer import BvhWriter
    from firmware_bridge.outputs.vrchat import VrchatSender
    pose, k = synthetic_motion(1)[0], 1.60 / 1.75
    with VmcSender(LOOPBACK, receiver.getsockname()[1], mode="bundle", scale=k) as vmc:
        vmc.send(pose, t=0.0)
    bones = {args[0]: np.array(args[1:]) for a, args in osc.decode_packet(receive(receiver, 1)[0]) if a.endswith("Bone/Pos")}
    assert np.allclose(bones["Hips"][:3], pose.positions[0] * k * [-1, 1, 1], atol=FLOAT32_TOL)
    assert np.allclose(bones["LeftLowerLeg"][:3], OFFSETS[JOINT["l_knee"]] * k * [-1, 1, 1], atol=FLOAT32_TOL)
    with VrchatSender(LOOPBACK, receiver.getsockname()[1], trackers=("pelvis",), send_head=False, scale=k) as vr:
        vr.send(pose)
    position = osc.decode_packet(receive(receiver, 2)[0])[0][1]
    assert np.allclose(position, pose.positions[0] * k * [-1, 1, 1], atol=FLOAT32_TOL)
    with BvhWriter(tmp_path / "k.bvh", scale=k) as bvh:
        bvh.send(pose)
    from motion import bvh as bvh_file
    clip = bvh_file.load(tmp_path / "k.bvh")
    named = {n: clip.offsets[i] / 100.0 for i, n in enumerate(clip.names) if n in JOINT}
    assert len(named) == len(OFFSETS)
    assert all(np.allclose(named[n], OFFSETS[JOINT[n]] * k, atol=1e-4) for n in named if JOINT[n] > 0)
    assert np.allclose(clip.positions[0, 0] / 100.0, pose.positions[0] * k, atol=1e-4)
