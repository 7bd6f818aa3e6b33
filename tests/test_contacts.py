"""Foot-contact labels from motion (motion.contacts): a planted foot is in contact, a swinging or raised one is not."""
import numpy as np

from motion.contacts import contact_labels, savgol


def test_savgol_preserves_cubics_away_from_edges():
    t = np.linspace(-1, 1, 50)
    x = 2 * t ** 3 - t + 0.5
    assert np.allclose(savgol(x)[6:-6], x[6:-6])


def test_planted_foot_is_in_contact_and_swinging_foot_is_not():
    fps, T = 60.0, 240
    t = np.arange(T) / fps
    toes = np.zeros((T, 2, 3))
    toes[:, :, 1] = 0.02
    # Right foot swings: 10 cm high arcs, moving forward at 1 m/s.
    toes[:, 1, 1] = 0.02 + 0.10 * np.abs(np.sin(np.pi * t))
    toes[:, 1, 2] = t
    c = contact_labels(toes, fps)
    assert c[:, 0].mean() == 1.0
    assert c[20:-20, 1].mean() < 0.05


def test_slow_foot_above_the_height_threshold_is_not_in_contact():
    T = 120
    toes = np.zeros((T, 2, 3))
    toes[:, 0, 1] = 0.02
    toes[:, 1, 1] = 0.02
    toes[60:, 1, 1] = 0.2  # raised and held still
    c = contact_labels(toes)
    assert c[70:, 1].max() == 0 and c[:50, 1].min() == 1
