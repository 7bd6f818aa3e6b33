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


def test_height_scale_maps_the_user_onto_the_canonical_body():
    K = 10
    cal = calibrate(np.tile([0, 1.50, 0], (K, 1)), np.tile([1.0, 0, 0, 0], (K, 1)), {})
    assert cal.height_scale == pytest.approx(CANONICAL_EYE_HEIGHT / 1.50)


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
