"""Standing calibration: mounting offsets, heading alignment and height scale."""
import numpy as np
import pytest

from edge import quat
from edge.calibration import CANONICAL_EYE_HEIGHT, Calibration, CalibrationError, calibrate


def rot(axis, deg):
    return quat.from_axis_angle(np.array(axis, dtype=float), np.radians(deg))


def test_calibrated_tracker_reports_the_body_orientation_through_turns():
    mount = rot([1, 0, 0], 80)                  # puck strapped on tilted by 80 degrees
    imu_ref = rot([0, 1, 0], 35)                # the IMU's heading reference differs from the headset's
    heading = rot([0, 1, 0], -20)               # the user faces -20 degrees during calibration
    sensor = lambda body: quat.mul(quat.mul(quat.inv(imu_ref), body), quat.inv(mount))
    K = 30
    cal = calibrate(np.tile([0, 1.62, 0], (K, 1)), np.tile(heading, (K, 1)), {"waist": np.tile(sensor(heading), (K, 1))})
    for body in (heading, quat.mul(rot([0, 1, 0], 90), heading), rot([0, 1, 0], 170)):
        got = cal.body_rotation("waist", sensor(body))
        assert np.degrees(quat.angle(quat.mul(quat.inv(body), got))) < 1e-4


def test_calibrated_headset_reads_the_head_whatever_way_it_sits_on_the_face():
    """A headset worn pitched 9 degrees and rolled 4 against a level head reads the head itself after a
    T-pose calibration (looking ahead), through turns and nods; uncalibrated it keeps the tilt."""
    from edge.calibration import FrameCalibration
    from edge.signals import Signals
    worn = quat.mul(rot([1, 0, 0], 9), rot([0, 0, 1], 4))
    facing = rot([0, 1, 0], 40)
    K = 20
    cal = calibrate(np.tile([0, 1.7, 0], (K, 1)), np.tile(quat.mul(facing, worn), (K, 1)), {})
    assert abs(np.degrees(cal.heading) - 40) < 1.0
    frame = FrameCalibration(cal)
    for head in (facing, quat.mul(rot([0, 1, 0], -70), facing), quat.mul(facing, rot([1, 0, 0], 30))):
        sig = Signals(np.zeros((1, 3)), quat.mul(head, worn)[None], np.zeros((1, 2, 3)), np.tile([1.0, 0, 0, 0], (1, 2, 1)),
                      np.array([[1.0, 0, 0, 0]]), np.zeros((1, 3)))
        assert np.degrees(quat.angle(quat.mul(quat.inv(head), frame(sig).head_rot[0]))) < 1e-6
        assert np.degrees(quat.angle(quat.mul(quat.inv(head), sig.head_rot[0]))) > 9.0


def test_height_scale_maps_the_users_head_joint_onto_the_canonical_one_and_keeps_the_devices_offsets():
    """A user whose headset stands 1.50 m high: their head joint (the eyes are a headset's offset in front
    of and above it, whatever the person's size) lands on the canonical body's, and the eyes and the
    controllers' grips keep their offsets from the head and wrists (issue #54: scaling the grip with the
    body put a short user's wrists 1.2 cm off the controllers)."""
    from edge.calibration import FrameCalibration
    from edge.signals import EYE_OFFSET, GRIP_OFFSET, Signals
    K = 10
    cal = calibrate(np.tile([0, 1.50, 0], (K, 1)), np.tile([1.0, 0, 0, 0], (K, 1)), {})
    assert cal.height_scale == pytest.approx((CANONICAL_EYE_HEIGHT - EYE_OFFSET[1]) / (1.50 - EYE_OFFSET[1]))
    assert cal.eye_height_m == pytest.approx(1.50) and cal.stature_m() == pytest.approx(1.50 / 0.936)
    head_rot, hand_rot = rot([0, 1, 0], 30), np.stack([rot([1, 0, 0], 50), rot([0, 0, 1], -40)])
    wrists = np.array([[0.3, 1.0, 0.2], [-0.3, 0.9, 0.1]])
    head_joint = np.array([0.05, 1.40, 0.02])
    sig = Signals((head_joint + quat.rotate(head_rot, EYE_OFFSET))[None], head_rot[None],
                  (wrists + quat.rotate(hand_rot, GRIP_OFFSET))[None], hand_rot[None], np.array([[1.0, 0, 0, 0]]),
                  np.zeros((1, 3)))
    cal.mount.clear()                                  # levelling aside: the positions only
    out = FrameCalibration(cal)(sig)
    s = cal.height_scale
    np.testing.assert_allclose(out.head_pos[0] - quat.rotate(head_rot, EYE_OFFSET), head_joint * s, atol=1e-12)
    np.testing.assert_allclose(out.hand_pos[0] - quat.rotate(hand_rot, GRIP_OFFSET), wrists * s, atol=1e-12)


def test_a_calibration_file_from_before_loads_with_its_eye_height_kept(tmp_path):
    """Version 1 files kept the eyes' ratio only: they load, the eye height they measured recovered and
    the head joint's ratio made from it; a stature in the config wins over the measured one."""
    import json
    from edge.signals import EYE_OFFSET
    old = tmp_path / "v1.json"
    old.write_text(json.dumps({"version": 1, "height_scale": CANONICAL_EYE_HEIGHT / 1.55, "heading_deg": 10.0,
                               "trackers": {}}))
    cal = Calibration.load(old)
    assert cal.eye_height_m == pytest.approx(1.55)
    assert cal.height_scale == pytest.approx((CANONICAL_EYE_HEIGHT - EYE_OFFSET[1]) / (1.55 - EYE_OFFSET[1]))
    cal.save(tmp_path / "v2.json")
    assert json.loads((tmp_path / "v2.json").read_text())["version"] == 2
    assert Calibration.load(tmp_path / "v2.json").height_scale == pytest.approx(cal.height_scale)
    tall = cal.with_stature(1.92)
    assert tall.stature_m() == pytest.approx(1.92) and tall.height_scale < 1.0 < cal.height_scale


def test_sitting_calibration_is_refused():
    with pytest.raises(CalibrationError, match="stand upright"):
        calibrate(np.tile([0, 0.6, 0], (5, 1)), np.tile([1.0, 0, 0, 0], (5, 1)), {})


def test_round_trip_and_clear_errors_for_bad_files(tmp_path):
    K = 5
    cal = calibrate(np.tile([0, 1.7, 0], (K, 1)), np.tile([1.0, 0, 0, 0], (K, 1)), {"waist": np.tile(rot([1, 0, 0], 10), (K, 1))})
    cal.save(tmp_path / "c.json")
    back = Calibration.load(tmp_path / "c.json")
    assert back.height_scale == pytest.approx(cal.height_scale)
    assert np.allclose(back.mount["waist"], cal.mount["waist"])
    with pytest.raises(CalibrationError, match="edge calibrate"):
        Calibration.load(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(CalibrationError, match="not a valid calibration"):
        Calibration.load(tmp_path / "bad.json")
    (tmp_path / "tall.json").write_text('{"version": 1, "height_scale": 7}')
    with pytest.raises(CalibrationError, match="implausible"):
        Calibration.load(tmp_path / "tall.json")


def test_a_height_in_the_config_is_read_and_a_wrong_one_refused_with_the_fix():
    from firmware_bridge import config as config_mod
    raw = {"headset": {"url": "serial:///dev/ttyAMA0?role=headset"}, "body": {"height_m": 1.62}}
    from firmware_bridge.wiring import load_calibration
    cfg = config_mod.from_dict(raw)
    assert cfg.height_m == 1.62 and load_calibration(cfg).stature_m() == pytest.approx(1.62)     # what the board uses
    assert config_mod.from_dict({"headset": raw["headset"]}).height_m is None
    for bad in (162, "tall", True):
        with pytest.raises(config_mod.ConfigError, match=r"\[body\] height_m is the user's height in metres"):
            config_mod.from_dict({**raw, "body": {"height_m": bad}})


def test_the_arms_length_is_measured_from_the_controllers_held_out_and_refused_with_arms_down():
    """#54 item 2, the T-pose's part: on bodies with arms 8 % short or long for their height, three
    statures, the controllers held out at the sides give the arm (shoulder to wrist) within 2 cm; arms
    hanging down, or a controller lost, say what to do."""
    from edge.calibration import arm_length_from_tpose, height_scale_for
    from edge.signals import GRIP_OFFSET
    from edge.skeleton import JOINT, TOE_HEIGHT, rest_positions
    from motion.bodies import Body, eye_height
    K = 40
    rng = np.random.default_rng(0)
    for body in (Body("a", 1.55, arms=0.92), Body("b", 1.75, arms=1.08), Body("c", 1.95, legs=1.08, arms=1.0)):
        off = body.offsets()
        rest = rest_positions(off)
        rest[:, 1] += TOE_HEIGHT - rest[JOINT["l_toe"], 1]            # standing on the floor
        wrists = rest[[JOINT["l_wrist"], JOINT["r_wrist"]]]
        hand_rot = np.tile([1.0, 0, 0, 0], (K, 2, 1))
        hand_pos = wrists + GRIP_OFFSET + rng.normal(0, 0.003, (K, 2, 3))        # a person holds still, nearly
        truth = np.linalg.norm(off[JOINT["l_elbow"]]) + np.linalg.norm(off[JOINT["l_wrist"]])
        scale = height_scale_for(eye_height(off))
        arm = arm_length_from_tpose(hand_pos, hand_rot, np.ones((K, 2), bool), scale)
        assert arm == pytest.approx(truth, abs=0.02), body
    down = hand_pos.copy()
    down[:, 0, 1] -= 0.6
    with pytest.raises(CalibrationError, match="straight out"):
        arm_length_from_tpose(down, hand_rot, np.ones((K, 2), bool), scale)
    lost = np.ones((K, 2), bool)
    lost[: K // 2, 1] = False
    with pytest.raises(CalibrationError, match="not tracked"):
        arm_length_from_tpose(hand_pos, hand_rot, lost, scale)


def _worn_calibration():
    """A T-pose calibration of a 1.62 m headset worn tilted, a waist puck and two extra IMUs, each
    mounted and referenced their own way."""
    rng = np.random.default_rng(7)
    K = 12
    face = rot([0, 1, 0], 25)
    trackers = {name: np.tile(quat.normalize(rng.standard_normal(4)), (K, 1)) for name in ("waist", "l_shin", "r_thigh")}
    return calibrate(np.tile([0.1, 1.62, -0.2], (K, 1)), np.tile(quat.mul(face, rot([1, 0, 0], 8)), (K, 1)), trackers)


def test_the_calibrated_frame_is_the_product_a_q_m_and_the_offsets_kept():
    """FrameCalibration's matrices give what the quaternion products and devices_on_canonical give."""
    from edge.calibration import FrameCalibration, devices_on_canonical
    from edge.imus import IMU_LOCATIONS, NUM_IMUS
    from edge.signals import Signals
    cal = _worn_calibration()
    slots = [(n, IMU_LOCATIONS.index(n)) for n in ("l_shin", "r_thigh")]
    frame = FrameCalibration(cal, slots)
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = lambda *shape: quat.normalize(rng.standard_normal(shape + (4,)))    # noqa: E731
        sig = Signals(rng.uniform(-1, 2, (1, 3)), q(1), rng.uniform(-1, 2, (1, 2, 3)), q(1, 2), q(1),
                      rng.standard_normal((1, 3)), q(1, NUM_IMUS), rng.uniform(0, 1, (1, NUM_IMUS)))
        out = frame(sig)
        head_rot = cal.body_rotation("head", sig.head_rot)
        np.testing.assert_allclose(out.head_rot, head_rot, atol=1e-12)
        np.testing.assert_allclose(out.waist_rot, cal.body_rotation("waist", sig.waist_rot), atol=1e-12)
        want_imu = sig.imu_rot.copy()
        for name, k in slots:
            want_imu[0, k] = cal.body_rotation(name, sig.imu_rot[0, k])
        np.testing.assert_allclose(out.imu_rot, want_imu, atol=1e-12)
        head_pos, hand_pos = devices_on_canonical(sig.head_pos, head_rot, sig.hand_pos, sig.hand_rot, cal.height_scale)
        np.testing.assert_allclose(out.head_pos, head_pos, atol=1e-12)
        np.testing.assert_allclose(out.hand_pos, hand_pos, atol=1e-12)
        for name in ("hand_rot", "waist_acc", "imu_flag"):
            np.testing.assert_array_equal(getattr(out, name), getattr(sig, name))


def test_the_calibrated_frame_makes_no_arrays():
    """FrameCalibration runs every frame on the board: it allocates no arrays. tracemalloc sees numpy's
    buffers and its views' headers (~150 bytes each, a few alive at once: ~600 at peak); the quaternion
    products it replaced peaked at 5,960."""
    import tracemalloc
    from edge.calibration import FrameCalibration
    from edge.imus import IMU_LOCATIONS, NUM_IMUS
    from edge.signals import Signals
    frame = FrameCalibration(_worn_calibration(), [("l_shin", IMU_LOCATIONS.index("l_shin"))])
    sig = Signals(np.ones((1, 3)), np.array([[1.0, 0, 0, 0]]), np.ones((1, 2, 3)), np.tile([1.0, 0, 0, 0], (1, 2, 1)),
                  np.array([[1.0, 0, 0, 0]]), np.zeros((1, 3)), np.tile([1.0, 0, 0, 0], (1, NUM_IMUS, 1)),
                  np.ones((1, NUM_IMUS)))
    frame(sig)
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        for _ in range(100):
            frame(sig)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert peak < 800, peak


def test_a_leg_length_in_the_config_gives_the_board_the_users_legs_or_fails_with_the_fix():
    """[body] leg_length_m (floor to hip joint, standing): legs long for the height are sent that long;
    a length no adult skeleton has at that height fails at start-up saying how to measure."""
    from edge.proportions import CANONICAL_HIP_HEIGHT
    from firmware_bridge import config as config_mod
    from firmware_bridge.wiring import load_calibration, user_body
    raw = {"headset": {"url": "serial:///dev/ttyAMA0?role=headset"}, "body": {"height_m": 1.75}}
    cfg = config_mod.from_dict(raw)
    assert cfg.leg_length_m is None and user_body(cfg, load_calibration(cfg)).canonical
    cal = load_calibration(cfg)
    canonical_legs_here = CANONICAL_HIP_HEIGHT / cal.height_scale           # the canonical legs at 1.75 m
    cfg = config_mod.from_dict({**raw, "body": {"height_m": 1.75, "leg_length_m": round(canonical_legs_here * 1.06, 3)}})
    body = user_body(cfg, load_calibration(cfg))
    assert 1.05 < body.legs < 1.08 and not body.canonical
    with pytest.raises(config_mod.ConfigError, match="bony point at the side of the hip"):
        user_body(config_mod.from_dict({**raw, "body": {"height_m": 1.75, "leg_length_m": 1.25}}), cal)
    for bad in ("long", True, 2.0):
        with pytest.raises(config_mod.ConfigError, match=r"\[body\] leg_length_m is floor to hip joint"):
            config_mod.from_dict({**raw, "body": {"leg_length_m": bad}})
    # the arms: the T-pose's measurement, and a [body] arm_length_m over it
    from edge.calibration import CANONICAL_ARM
    cal.arm_length_m = 1.06 * CANONICAL_ARM / cal.height_scale
    assert user_body(config_mod.from_dict(raw), cal).arms == pytest.approx(1.06)
    written = config_mod.from_dict({**raw, "body": {"height_m": 1.75, "arm_length_m": round(0.95 * CANONICAL_ARM / cal.height_scale, 4)}})
    assert user_body(written, cal).arms == pytest.approx(0.95, abs=1e-3)


def test_the_legs_are_measured_from_a_controller_held_at_the_hip_and_refused_when_it_cannot_be():
    """#54 item 2, the legs: on bodies with legs 8 % short or long for three statures, the left controller held
    still at the side of the hip (at the hip joint's height, a centimetre of tremor) gives legs within
    2 cm of the truth, the board's `legs` from it within 0.02; a moving, lost or misplaced controller
    says what to do."""
    from edge.calibration import height_scale_for, leg_length_from_hip
    from edge.proportions import legs_for
    from edge.skeleton import JOINT, TOE_HEIGHT, rest_positions
    from motion.bodies import Body, eye_height
    rng = np.random.default_rng(5)
    K = 90
    for height, legs in ((1.55, 0.92), (1.75, 1.08), (1.95, 0.92), (1.95, 1.08)):
        body = Body("b", height, legs)
        off = body.offsets()
        rest = rest_positions(off)
        hip = TOE_HEIGHT * body.leg_scale() + rest[JOINT["l_hip"], 1] - rest[JOINT["l_toe"], 1]
        pos = np.zeros((K, 2, 3))
        pos[:, 0] = [0.25, hip, 0.0] + rng.normal(0, 0.005, (K, 3))          # held at the hip
        pos[:, 1] = [-0.3, 0.85 * hip, 0.1]                                  # the other hand hanging, lower
        valid = np.ones((K, 2), bool)
        eye = eye_height(off)
        measured = leg_length_from_hip(pos, valid, eye)
        assert measured == pytest.approx(hip, abs=0.02)
        assert legs_for(measured, height_scale_for(eye)) == pytest.approx(legs, abs=0.02)
    moving = pos.copy()
    moving[:, 0, 1] += np.linspace(0, 0.2, K)
    with pytest.raises(CalibrationError, match="hold it still"):
        leg_length_from_hip(moving, valid, eye)
    lost = valid.copy()
    lost[: K // 2, 0] = lost[: K // 2, 1] = False
    with pytest.raises(CalibrationError, match="keep it in view"):
        leg_length_from_hip(pos, lost, eye)
    low = pos.copy()
    low[:, 0, 1] = 0.3
    with pytest.raises(CalibrationError, match="bony point at the side of the left hip, standing"):
        leg_length_from_hip(low, valid, eye)


def test_a_calibration_keeps_the_legs_it_measured_and_the_board_uses_them(tmp_path):
    from edge.proportions import CANONICAL_HIP_HEIGHT
    from firmware_bridge import config as config_mod
    from firmware_bridge.wiring import load_calibration, user_body
    cal = calibrate(np.tile([0, 1.62, 0], (10, 1)), np.tile([1.0, 0, 0, 0], (10, 1)), {})
    cal.leg_length_m = 1.06 * CANONICAL_HIP_HEIGHT / cal.height_scale
    cal.save(tmp_path / "cal.json")
    loaded = Calibration.load(tmp_path / "cal.json")
    assert loaded.leg_length_m == pytest.approx(cal.leg_length_m)
    cfg = config_mod.from_dict({"headset": {"url": "serial:///dev/ttyAMA0?role=headset"},
                                "runtime": {"calibration": str(tmp_path / "cal.json")}})
    body = user_body(cfg, load_calibration(cfg))
    assert 1.05 < body.legs < 1.09
    assert load_calibration(cfg).with_stature(1.8).leg_length_m == pytest.approx(cal.leg_length_m)
