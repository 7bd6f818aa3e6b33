"""`edge run` and `edge calibrate`: start-up checks with messages that say what to fix."""
import json
import sys
import time

import numpy as np

from edge.calibration import CalibrationError, calibrate as solve_calibration
from edge.progress import Progress
from edge.shutdown import StopSignals, replace_whole
from firmware_bridge import config as config_mod
from firmware_bridge.samples import HeadsetSample
from firmware_bridge.transports import TransportError


def _load(args):
    try:
        return config_mod.load(args.config)
    except config_mod.ConfigError as e:
        print(f"edge: {e}", file=sys.stderr)
        return None


def run(args):
    cfg = _load(args)
    if cfg is None:
        return 2
    from firmware_bridge.service import Service
    # SIGTERM (systemd) and Ctrl-C end the loop at its next tick, as its time limit does: the outputs
    # (the BVH's frame count) flushed and closed, the summary written (edge.shutdown).
    with StopSignals() as stop:
        try:
            service = Service(cfg, status=sys.stderr)      # the stderr of now, not of import time
        except (TransportError, CalibrationError) as e:
            print(f"edge run: {e}", file=sys.stderr)
            return 2
        summary = service.run(args.seconds, stop=stop.requested)
        if stop.requested():
            print(f"edge run: stopped by {stop.signal_name}; outputs closed", file=sys.stderr)
        if args.json:
            with replace_whole(args.json) as tmp:
                tmp.write_text(json.dumps(summary, indent=2) + "\n")
    return 0


def calibrate(args):
    cfg = _load(args)
    if cfg is None:
        return 2
    from firmware_bridge.links import Link
    try:
        links = [Link(u) for u in [cfg.headset] + cfg.trackers]
    except TransportError as e:
        print(f"edge calibrate: {e}", file=sys.stderr)
        return 2
    absent = [link for link in links if link.source is None]     # a T-pose needs every device there now
    if absent:
        for link in links:
            link.close()
        print(f"edge calibrate: {absent[0].start_error}", file=sys.stderr)
        return 2
    print("Stand upright, arms out to the sides (T-pose), facing forward. Hold still...", file=sys.stderr)
    try:
        with StopSignals() as stop:
            return _calibrate_poses(links, cfg, args, stop)
    finally:
        for link in links:
            link.close()


def _calibrate_poses(links, cfg, args, stop):
    """The T-pose (and with --legs the hand at the hip) measured and written to args.out."""
    heads, rots, hands, trackers = _collect(links, cfg.tracker_names, args.seconds, stop)
    if stop.requested():
        print(f"edge calibrate: stopped by {stop.signal_name} before the T-pose was measured; "
              f"{args.out} is as it was", file=sys.stderr)
        return 130
    missing = [n for n, q in trackers.items() if not q] + ([] if heads else ["headset"])
    if missing:
        print(f"edge calibrate: no data from {', '.join(missing)} in {args.seconds:.0f} s; check they are on and "
              f"configured", file=sys.stderr)
        return 2
    try:
        cal = solve_calibration(np.array(heads), np.array(rots), {n: np.array(q) for n, q in trackers.items()})
    except CalibrationError as e:
        print(f"edge calibrate: {e}", file=sys.stderr)
        return 2
    arms = _measure_arms(hands, cal, args.out)
    legs = (_measure_legs(links, args, cal, stop) if getattr(args, "legs", False)
            else _kept_legs(cal, args.out) + (" (--legs measures them)" if not cal.leg_length_m else ""))
    if stop.requested():
        print(f"edge calibrate: stopped by {stop.signal_name}; {args.out} is as it was", file=sys.stderr)
        return 130
    cal.save(args.out)
    print(f"wrote {args.out}: headset {cal.eye_height_m:.2f} m above the floor standing, so a body about "
          f"{cal.stature_m():.2f} m tall (height scale {cal.height_scale:.3f}; a [body] height_m in the config "
          f"overrides it), {arms}, {legs}, trackers {', '.join(cal.mount) or '-'}", file=sys.stderr)
    return 0


def _measure_legs(links, args, cal, stop):
    """--legs: the left controller held at the side of the hip for `seconds` gives the leg (floor to hip joint);
    when it cannot be measured, the previous file's is kept. -> what to say of it."""
    from edge.calibration import leg_length_from_hip
    print("Now hold the left controller against the bony point at the side of your left hip, standing. "
          "Hold still...", file=sys.stderr)
    _, _, hands, _ = _collect(links, (), args.seconds, stop)
    try:
        pos, valid = np.array([h[0] for h in hands]), np.array([h[2] for h in hands])
        cal.leg_length_m = leg_length_from_hip(pos, valid, cal.eye_height_m)
        return f"legs {cal.leg_length_m:.2f} m floor to hip"
    except (CalibrationError, ValueError, IndexError) as e:
        return f"{_kept_legs(cal, args.out)} ({e})"


def _kept_legs(cal, previous_path):
    """The leg the previous calibration file measured, kept (the last good body). -> what to say of it."""
    from edge.calibration import Calibration
    try:
        cal.leg_length_m = Calibration.load(previous_path).leg_length_m
    except CalibrationError:
        cal.leg_length_m = None
    return f"legs kept {cal.leg_length_m:.2f} m from before" if cal.leg_length_m else "legs not measured"


def _collect(links, tracker_names, seconds, stop):
    """A pose's samples for `seconds` (or until a stop): the headset's positions and rotations, the
    controllers' (positions, rotations, tracked), each tracker's orientations."""
    heads, rots, hands, trackers = [], [], [], {name: [] for name in tracker_names}
    start = time.monotonic()
    with Progress(int(seconds * 10), "calibrate") as bar:
        while time.monotonic() - start < seconds and not stop.requested():
            for link in links:
                for s in link.drain(time.monotonic):
                    if isinstance(s, HeadsetSample):
                        heads.append(s.head_pos)
                        rots.append(s.head_rot)
                        hands.append((s.hand_pos, s.hand_rot, s.hand_valid))
                    elif s.tracker in trackers:
                        trackers[s.tracker].append(s.quat)
            time.sleep(0.005)
            bar.n = int((time.monotonic() - start) * 10) - 1
            bar.update()
    return heads, rots, hands, trackers


def _measure_arms(hands, cal, previous_path):
    """The arm length from the controllers in the T-pose, into `cal`; when it cannot be measured, the one
    the previous calibration file measured is kept (the last good body). -> what to say of it."""
    from edge.calibration import Calibration, arm_length_from_tpose
    try:
        pos, rot, valid = (np.array([h[k] for h in hands]) for k in range(3))
        cal.arm_length_m = arm_length_from_tpose(pos, rot, valid, cal.height_scale)
        return f"arms {cal.arm_length_m:.2f} m shoulder to wrist"
    except (CalibrationError, ValueError, IndexError) as e:
        try:
            cal.arm_length_m = Calibration.load(previous_path).arm_length_m
        except CalibrationError:
            cal.arm_length_m = None
        kept = f"kept {cal.arm_length_m:.2f} m from before" if cal.arm_length_m else "not measured"
        return f"arms {kept} ({e})"
