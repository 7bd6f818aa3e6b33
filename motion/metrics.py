"""Reconstruction metrics (SSI Table 1 and smoothness/contact measures), on world positions in metres."""
import numpy as np

from motion.contacts import contact_labels
from edge.physics import FLOAT_M, INTERSECT_M, PENETRATION_M, foot_height, leg_gap
from edge.skeleton import ANKLES, FEET, HEAD, JOINT, LOWER_BODY, WRISTS

KNEES = np.array([JOINT["l_knee"], JOINT["r_knee"]])

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
    per_joint = 100 * sum(p["per_joint_sum"] for p in parts) / frames
    return {
        "frames": int(frames),
        "mpjpe_cm": 100 * tot("mpjpe_sum") / frames,
        "mpjve_cm_s": 100 * tot("mpjve_sum") / max(tot("mpjve_n"), 1),
        "mpjae_cm_s2": 100 * tot("mpjae_sum") / max(tot("mpjae_n"), 1),
        "jitter_m_s3": tot("jitter_sum") / max(tot("jitter_n"), 1),
        "ee_error_cm": 100 * tot("ee_sum") / frames,
        "foot_skate_cm_s": 100 * tot("skate_sum") / max(tot("skate_n"), 1),
        "implausible_rate": tot("implausible_sum") / frames,
        "knees_cm": float(per_joint[KNEES].mean()), "ankles_cm": float(per_joint[ANKLES].mean()),
        "per_joint_mpjpe_cm": per_joint.round(3).tolist(),
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


def physical_metrics(pos, contacts):
    """Physical plausibility of a clip (SSI 3.2 and 5.3's constraints), as sums and counts.
    pos [T,J,3] world metres, floor at y = 0; contacts [T,2] what the output (or the truth) says."""
    depth = np.maximum(-pos[:, np.concatenate([ANKLES, FEET]), 1], 0).max(-1)     # deepest foot joint, [T]
    sinks = depth > PENETRATION_M
    floats = ((contacts > 0.5) & (foot_height(pos) > FLOAT_M)).any(-1)
    return {"frames": len(pos), "penetration_n": int(sinks.sum()), "penetration_depth_sum": float(depth[sinks].sum()),
            "intersect_n": int((leg_gap(pos) < INTERSECT_M).sum()), "float_n": int(floats.sum())}


def summarize_physical(parts):
    """Sums from physical_metrics -> rates and the mean depth (cm) of the frames that sink."""
    tot = {k: sum(p[k] for p in parts) for k in parts[0]} if parts else {}
    n = max(tot.get("frames", 0), 1)
    return {"penetration_rate": tot.get("penetration_n", 0) / n,
            "penetration_cm": 100 * tot.get("penetration_depth_sum", 0) / max(tot.get("penetration_n", 0), 1),
            "leg_intersect_rate": tot.get("intersect_n", 0) / n, "float_rate": tot.get("float_n", 0) / n,
            "physical_sum": (tot.get("penetration_n", 0) + tot.get("intersect_n", 0) + tot.get("float_n", 0)) / n}


def diversity_metrics(samples, gt):
    """What N samples offer SSI (N > 1), as sums. samples [T,N,J,3] every sample's pose of a frame, gt [T,J,3].
    apd: mean pairwise lower-body distance between samples; oracle: the best sample per frame (all joints);
    the oracle's lower-body error against the average sample's."""
    T, N = samples.shape[:2]
    err = np.linalg.norm(samples - gt[:, None], axis=-1)                     # [T,N,J]
    lower = err[..., LOWER_BODY].mean(-1)                                    # [T,N]
    low = samples[:, :, LOWER_BODY]
    pair = np.linalg.norm(low[:, :, None] - low[:, None], axis=-1).mean(-1)  # [T,N,N]
    apd = pair.sum((1, 2)) / (N * (N - 1))
    return {"frames": T, "apd_lower_sum": float(apd.sum()), "oracle_sum": float(err.mean(-1).min(-1).sum()),
            "oracle_lower_sum": float(lower.min(-1).sum()), "average_lower_sum": float(lower.mean(-1).sum())}


def summarize_diversity(parts):
    if not parts:
        return {}
    tot = {k: sum(p[k] for p in parts) for k in parts[0]}
    n = max(tot["frames"], 1)
    return {"apd_lower_cm": 100 * tot["apd_lower_sum"] / n, "oracle_mpjpe_cm": 100 * tot["oracle_sum"] / n,
            "oracle_lower_cm": 100 * tot["oracle_lower_sum"] / n, "average_sample_lower_cm": 100 * tot["average_lower_sum"] / n,
            "oracle_to_average_lower": tot["oracle_lower_sum"] / max(tot["average_lower_sum"], 1e-12)}
