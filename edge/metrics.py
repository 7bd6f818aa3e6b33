"""Reconstruction metrics (SSI Table 1 and smoothness/contact measures), on world positions in metres."""
import numpy as np

from edge.contacts import contact_labels
from edge.skeleton import FEET, HEAD, WRISTS


def clip_metrics(pred, gt, fps, tracked_head, tracked_wrists, implausible):
    """pred, gt [T,J,3]; tracked_* [T,3] / [T,2,3]; implausible [T] bool. Sums and counts, so clips aggregate by frame."""
    T = len(pred)
    err = np.linalg.norm(pred - gt, axis=-1)                       # [T,J]
    vp, vg = np.diff(pred, axis=0) * fps, np.diff(gt, axis=0) * fps
    ap, ag = np.diff(vp, axis=0) * fps, np.diff(vg, axis=0) * fps
    jerk = np.diff(ap, axis=0) * fps
    ee = np.concatenate([np.linalg.norm(pred[:, HEAD] - tracked_head, axis=-1)[:, None],
                         np.linalg.norm(pred[:, WRISTS] - tracked_wrists, axis=-1)], axis=1)
    contact = contact_labels(gt[:, FEET], fps)[1:] > 0.5                 # [T-1,2]
    foot_speed = np.linalg.norm(vp[:, FEET][..., [0, 2]], axis=-1)       # horizontal
    return {
        "frames": T,
        "mpjpe_sum": err.mean(-1).sum(),
        "mpjve_sum": np.linalg.norm(vp - vg, axis=-1).mean(-1).sum(), "mpjve_n": len(vp),
        "mpjae_sum": np.linalg.norm(ap - ag, axis=-1).mean(-1).sum(), "mpjae_n": len(ap),
        "jitter_sum": np.linalg.norm(jerk, axis=-1).mean(-1).sum(), "jitter_n": len(jerk),
        "ee_sum": ee.mean(-1).sum(),
        "skate_sum": foot_speed[contact].sum(), "skate_n": int(contact.sum()),
        "implausible_sum": int(np.sum(implausible)),
        "per_joint_sum": err.sum(0),
    }


def summarize(parts):
    def tot(k):
        return float(sum(p[k] for p in parts))
    frames = tot("frames")
    return {
        "frames": int(frames),
        "mpjpe_cm": 100 * tot("mpjpe_sum") / frames,
        "mpjve_cm_s": 100 * tot("mpjve_sum") / max(tot("mpjve_n"), 1),
        "mpjae_cm_s2": 100 * tot("mpjae_sum") / max(tot("mpjae_n"), 1),
        "jitter_m_s3": tot("jitter_sum") / max(tot("jitter_n"), 1),
        "ee_error_cm": 100 * tot("ee_sum") / frames,
        "foot_skate_cm_s": 100 * tot("skate_sum") / max(tot("skate_n"), 1),
        "implausible_rate": tot("implausible_sum") / frames,
        "per_joint_mpjpe_cm": (100 * sum(p["per_joint_sum"] for p in parts) / frames).round(3).tolist(),
    }


def jerk_per_frame(pred, fps):
    """Mean joint jerk magnitude per frame [T-3] (m/s^3), aligned so entry i covers frames i..i+3."""
    jerk = np.diff(pred, n=3, axis=0) * fps ** 3
    return np.linalg.norm(jerk, axis=-1).mean(-1)


def transition_peaks(pred, fps, switch_starts, window_s=1.0):
    """RPM-style transition check: peak jerk in the window after each switch, and the peak jerk of
    every window of the same length that contains no switch. Returns (after_switch, quiet) lists."""
    j = jerk_per_frame(pred, fps)
    w = int(round(window_s * fps))
    starts = sorted(s for s in switch_starts if 0 <= s < len(j))
    after = [float(j[s:s + w].max()) for s in starts if s + w <= len(j)]
    busy = np.zeros(len(j), bool)
    for s in starts:
        busy[max(s - 3, 0):s + w] = True
    quiet = [float(j[a:a + w].max()) for a in range(0, len(j) - w + 1, w) if not busy[a:a + w].any()]
    return after, quiet
