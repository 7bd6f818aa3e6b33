"""The report of one replay: the service's summary, the stream's metrics, tracker health over time."""
import os

import numpy as np


def report(session, summary, m, service, ear, opened, errors, faults, speed, duration, resume_s):
    hz = service.cfg.hz
    lat = m.latency[np.isfinite(m.latency)]
    lat = lat if len(lat) else np.zeros(1)
    seen = np.flatnonzero(m.seen)
    out = {
        "source": session.name, "speed": speed, "seconds": duration, "faults": faults,
        "trackers": list(service.sync.trackers), "placement": session.meta.get("placement"),
        "slimevr": summary.get("slimevr", {}),
        "trackers_used_by_model": [n for n, _ in service.imu_slots] if service.pipeline.imus else [],
        "frames_in": summary["frames_in"], "frames_out": summary["frames_out"], "poses_decoded": m.decoded,
        "packets_corrupt": int(summary["packets_corrupt"] + ear.stats["corrupt"]),
        "packets_lost": int(summary["packets_lost"] + ear.stats.get("missed", 0)),
        "packets_unknown": int(summary.get("packets_unknown", 0)),
        "tracker_lost_events": summary["tracker_lost_events"], "deadline_misses": summary["deadline_misses"],
        "latency_ms": {"p50": float(np.median(lat)), "p99": float(np.percentile(lat, 99)), "max": float(lat.max())},
        "latency_note": "wall time from the start of the tick that produced a pose to its decoding by the host "
                        "reader (processing, serial transfer, decoding); the deliberate delays (SSI look-ahead, and the "
                        "synchroniser interpolating one headset period back) are reported apart",
        "lookahead_ms": 1000.0 * service.pipeline.lookahead / hz,
        "pose_age_ms": summary["pose_age_ms"], "motion_to_pose_lag_ms": summary["motion_to_pose_lag_ms"],
        "lag_note": summary["lag_note"],
        "sync_delay_ms": 1000.0 * service.cfg.sync_latency, "ssi_switches": service.pipeline.switch_count,
        "samples": service.pipeline.samples, "samples_max": summary["samples_max"], "precision": service.pipeline.precision,
        "precision_note": service.pipeline.precision_note,
        "samples_changes": summary["samples_changes"], "frame_ms": summary["frame_ms"], "reopens": summary["reopens"],
        "device_errors": summary.get("device_errors", 0), "clock_jumps": summary.get("clock_jumps", 0),
        "packets_corrupt_by_kind": summary.get("packets_corrupt_by_kind", {}),
        "reader_threads": summary.get("reader_threads", 0), "polls_held": summary.get("polls_held", 0), "samples_dropped": summary.get("samples_dropped", 0),
        "compiled_core": summary.get("compiled_core"),
        "output_errors": summary["output_errors"], "resume_after_replug_s": resume_s,
        "devices_down_at_start": summary.get("start_errors", {}),
        "missing_output_frames": int(len(seen) and (seen[-1] - seen[0] + 1 - len(seen))),
        "transports": {"opened": sorted(set(opened))}, "errors": errors,
        "latency_ms_samples": [round(float(x), 3) for x in lat[:20000]],
        "health_timeline": health_timeline(service.health_changes, duration, faults),
    }
    if faults.get("tracker_unplug") == "slimevr":      # a SlimeVR tracker silent, then re-handshaking
        macs = session.meta.get("slimevr_trackers", {})
        name = list(macs.values())[-1] if macs else None
        back_at = faults.get("tracker_unplug_at", 0) + faults.get("tracker_unplug_s", 2.0)
        back = [t for t, src, lost in service.health_changes if src == name and not lost and t >= back_at]
        out["slimevr_restart"] = {"tracker": name, "silent_from_s": faults.get("tracker_unplug_at"),
                                  "restarts_at_s": back_at, "in_use_again_after_s": (back[0] - back_at) if back else None}
    if "tracker_unplug_at" in faults:       # the pose around an extra IMU's loss: no pop
        at, ok = faults["tracker_unplug_at"], np.isfinite(m.step)
        before = m.step[ok & (m.t >= at - 1) & (m.t < at)]
        after = m.step[ok & (m.t >= at) & (m.t < at + 1)]
        if len(before) and len(after):
            out["tracker_unplug"] = {"tracker": faults.get("tracker_unplug"), "at_s": at,
                                     "largest_step_before_m": float(before.max()), "largest_step_after_m": float(after.max()),
                                     "ratio": float(after.max() / before.max())}
    err = m.error[np.isfinite(m.error)]
    if len(err):
        out["mpjpe_cm"] = float(err.mean() * 100)
    if m.jerk_n:
        out["jitter_m_s3"] = m.jerk_sum / m.jerk_n
    return out


def health_timeline(changes, duration, faults, step=0.1):
    """Lost flags per source on a 10 Hz grid, and the injected faults, in the format viz draws."""
    t = np.arange(0.0, duration, step)
    lost = {}
    for when, name, is_lost in changes:
        flags = lost.setdefault(name, np.zeros(len(t), np.int8))
        flags[t >= when] = 1 if is_lost else 0
    return {"t": [round(x, 3) for x in t], "lost": {k: v.tolist() for k, v in lost.items()},
            "faults": injected(faults)}


def injected(faults):
    """The faults a replay injected, as timeline marks: the timed ones where they happen, and those that
    run the whole take (drops, loss, bit errors, noise) at t = 0, saying how much."""
    marks = [{"t": faults[f"{k}_at"], "kind": k.replace("_", "-")} for k in ("unplug", "busoff", "clock_jump")
             if f"{k}_at" in faults]
    if "tracker_unplug_at" in faults:
        marks.append({"t": faults["tracker_unplug_at"], "kind": f"unplug {faults.get('tracker_unplug', 'tracker')}"})
    whole = {"disconnect": lambda f: f"IMU drops {100 * f['disconnect']:g} %/frame (DragPoser)",
             "loss": lambda f: f"packet loss {100 * f['loss']:g} %",
             "ber": lambda f: f"bit errors {f['ber']:g}/bit",
             "hand_loss": lambda f: f"controller loss {100 * f['hand_loss']:g} %/frame",
             "noise": lambda f: "device noise",
             "i2c_error_rate": lambda f: f"I2C errors {100 * f['i2c_error_rate']:g} %",
             "i2c_block_ms": lambda f: f"I2C read stalls {f['i2c_block_ms']:g} ms",
             "slimevr_flood_pps": lambda f: f"UDP flood {f['slimevr_flood_pps']:g}/s"}
    marks += [{"t": 0.0, "kind": say(faults)} for key, say in whole.items() if faults.get(key)]
    return marks


def rss_mb():
    with open(f"/proc/{os.getpid()}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024.0
