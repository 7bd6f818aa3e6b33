"""Tracker synthesis and the model's input features: the same code path for training and the board."""
import numpy as np

from edge import quat
from edge.features import (NUM_DECODER_FEATURES, body_points, derive_waist_position, heading, orientation_features,
                           sequence_features)
from motion.synth import DeviceNoise, synthesize
from edge.skeleton import JOINT, NUM_JOINTS, PELVIS_HEIGHT, fk


def walking_motion(T=120, fps=60.0):
    rot = np.tile([1.0, 0, 0, 0], (T, NUM_JOINTS, 1))
    phase = np.sin(np.arange(T) / fps * 2 * np.pi)
    x = np.array([1.0, 0, 0])
    rot[:, JOINT["l_hip"]] = quat.from_axis_angle(x, 0.4 * phase)
    rot[:, JOINT["r_hip"]] = quat.from_axis_angle(x, -0.4 * phase)
    rot[:, JOINT["l_shoulder"]] = quat.from_axis_angle(np.array([0, 0, 1.0]), -1.2 + 0.2 * phase)
    root = np.stack([np.zeros(T), np.full(T, PELVIS_HEIGHT), np.arange(T) / fps * 1.2], -1)
    return rot, root


def test_features_do_not_depend_on_where_the_user_stands_or_faces():
    rot, root = walking_motion()
    f0, _, _ = sequence_features(synthesize(rot, root, 60.0), 60.0)
    turn = quat.from_yaw(np.array(2.1))
    rot2 = rot.copy()
    rot2[:, 0] = quat.mul(turn, rot[:, 0])
    root2 = quat.rotate(turn, root) + np.array([3.0, 0.0, -5.0])
    f1, _, _ = sequence_features(synthesize(rot2, root2, 60.0), 60.0)
    assert np.allclose(f0, f1, atol=1e-9)
    o0, _, _ = sequence_features(synthesize(rot, root, 60.0), 60.0, n_features=NUM_DECODER_FEATURES)
    o1, _, _ = sequence_features(synthesize(rot2, root2, 60.0), 60.0, n_features=NUM_DECODER_FEATURES)
    assert o0.shape[-1] == NUM_DECODER_FEATURES and np.allclose(o0[:, :f0.shape[-1]], f0)
    assert np.allclose(o0, o1, atol=1e-9)       # the orientations too are in the character's frame


def test_orientation_features_are_the_headset_and_controllers_in_the_character_frame():
    """The 18 orientation features (the decoder's upper-body head reads them): in the T-pose each is the
    identity's 6D; the headset pitched down 30 degrees reads as that pitch whatever way the user faces."""
    rot, root = walking_motion(T=4)
    rot[:] = [1.0, 0, 0, 0]
    sig = synthesize(rot, root, 60.0)
    identity = np.array([1.0, 0, 0, 0, 1, 0])
    f, _, _ = sequence_features(sig, 60.0, n_features=NUM_DECODER_FEATURES)
    np.testing.assert_allclose(f[:, -18:], np.tile(identity, (4, 3)), atol=1e-12)
    pitch = quat.from_axis_angle(np.array([1.0, 0, 0]), np.radians(30))
    for yaw in (0.0, 2.5):
        turn = quat.from_yaw(np.array(yaw))
        sig.waist_rot = np.broadcast_to(turn, sig.waist_rot.shape).copy()
        sig.head_rot = np.broadcast_to(quat.mul(turn, pitch), sig.head_rot.shape).copy()
        head = orientation_features(sig.head_rot, sig.hand_rot, heading(sig.waist_rot))[:, :6]
        np.testing.assert_allclose(head, np.tile(quat.matrix_to_6d(quat.to_matrix(pitch)), (4, 1)), atol=1e-12)


def test_waist_is_exact_when_the_spine_is_straight():
    rot, root = walking_motion()
    sig = synthesize(rot, root, 60.0)
    points, _ = body_points(sig)
    assert np.allclose(points[:, 3], root, atol=1e-9)


def test_velocity_features_are_zero_when_standing_still():
    rot, root = walking_motion(T=30)
    rot[:] = rot[:1]
    root[:] = root[:1]
    f, _, _ = sequence_features(synthesize(rot, root, 60.0), 60.0)
    assert np.allclose(f[:, 12:], 0, atol=1e-9)
    assert np.allclose(f[:, 12 - 3:12:2], 0)  # the waist sits at the local origin in X and Z


def test_headset_sits_at_the_eyes_and_controllers_at_the_grip():
    rot, root = walking_motion(T=10)
    sig = synthesize(rot, root, 60.0)
    wr, pos = fk(quat.to_matrix(rot), root)
    assert np.allclose(np.linalg.norm(sig.head_pos - pos[:, JOINT["head"]], axis=-1), np.hypot(0.09, 0.09))
    d = np.linalg.norm(sig.hand_pos - pos[:, [JOINT["l_wrist"], JOINT["r_wrist"]]], axis=-1)
    assert np.allclose(d, np.linalg.norm([0.07, 0.02, 0.02]))


def test_device_noise_has_the_lobstr_scale():
    rot, root = walking_motion(T=6000)
    clean = synthesize(rot, root, 60.0)
    noisy = synthesize(rot, root, 60.0, np.random.default_rng(0), DeviceNoise())
    dpos = np.linalg.norm(noisy.head_pos - clean.head_pos, axis=-1)
    assert 0.005 < np.sqrt(np.mean(dpos ** 2)) / np.sqrt(3) < 0.02
    drot = np.degrees(quat.angle(quat.mul(quat.inv(clean.hand_rot), noisy.hand_rot)))
    assert drot.max() <= 1.5 + 1e-6
    # The puck's heading drifts; its tilt does not.
    dyaw = np.degrees(quat.yaw(noisy.waist_rot) - quat.yaw(clean.waist_rot))
    assert np.std(np.diff(dyaw)) < 1.0 and np.ptp(dyaw) > 0.1


def test_derived_waist_follows_the_puck_tilt():
    head = np.array([0.0, 1.6, 0.0])
    tilt = quat.from_axis_angle(np.array([1.0, 0, 0]), np.radians(30))
    w = derive_waist_position(head, tilt)
    assert w[2] < -0.1  # pelvis pushed back when the trunk leans forward


def test_bent_hands_keep_the_wrists_and_bend_smoothly_by_about_the_asked_angle():
    """motion.synth.bend_hands (the bench's wrist bend): the grips move with the hands, so the wrist
    joints the features see stay put; the bend wanders slowly, with about the std asked for."""
    from edge.features import wrist_joints
    from motion.synth import bend_hands
    rot, root = walking_motion(T=3600)
    sig = synthesize(rot, root, 60.0)
    bent = bend_hands(sig, 60.0, np.random.default_rng(0), flex_std_deg=20.0, dev_std_deg=10.0)
    assert np.allclose(wrist_joints(bent.hand_pos, bent.hand_rot), wrist_joints(sig.hand_pos, sig.hand_rot), atol=1e-9)
    angle = np.degrees(quat.angle(quat.mul(quat.inv(sig.hand_rot), bent.hand_rot)))
    assert 12.0 < np.sqrt(np.mean(angle ** 2)) < 35.0          # ~sqrt(20^2 + 10^2) = 22 deg
    bend = quat.mul(quat.inv(sig.hand_rot), bent.hand_rot)
    step = np.degrees(quat.angle(quat.mul(quat.inv(bend[1:]), bend[:-1])))
    assert step.max() < 6.0            # sines up to 1 Hz: < 360 deg/s; white noise of that std: ~30 deg a frame
