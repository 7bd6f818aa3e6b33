"""Foot-contact labels from joint positions (SSI section 4.1)."""
import numpy as np


def savgol_coeffs(window=11, order=3):
    """Savitzky-Golay smoothing weights (centre value of a least-squares polynomial fit)."""
    half = window // 2
    x = np.arange(-half, half + 1, dtype=np.float64)
    A = np.vander(x, order + 1, increasing=True)
    return np.linalg.pinv(A)[0]


def savgol(x, window=11, order=3):
    """Smooth along axis 0 (edges padded by reflection)."""
    half = window // 2
    if x.shape[0] < window:
        return x.copy()
    c = savgol_coeffs(window, order)
    pad = np.concatenate([x[half:0:-1], x, x[-2:-half - 2:-1]], axis=0)
    out = np.zeros_like(x, dtype=np.float64)
    for k in range(window):
        out += c[k] * pad[k:k + x.shape[0]]
    return out


def contact_labels(toe_pos, fps=60.0, height_margin=0.05, speed_cm_per_frame_60=1.0):
    """toe_pos [T,2,3] world metres -> contacts [T,2] in {0,1}.

    Height threshold: the lower of the two toes' 10th-percentile heights plus 5 cm, per sequence.
    Velocity: Savitzky-Golay (11, 3) smoothed toe speed below 1 cm per frame at 60 Hz.
    """
    height_thr = np.min(np.percentile(toe_pos[:, :, 1], 10, axis=0)) + height_margin
    vel = np.gradient(toe_pos, axis=0) * fps
    speed = np.linalg.norm(savgol(vel.reshape(len(vel), -1)).reshape(vel.shape), axis=-1)
    speed_thr = speed_cm_per_frame_60 * 0.01 * 60.0
    return ((toe_pos[:, :, 1] < height_thr) & (speed < speed_thr)).astype(np.float32)
