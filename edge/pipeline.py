"""The one per-frame path from tracker signals to a full-body pose.

`edge eval`, and later `edge run` and `edge replay`, drive this object; they differ only in where
frames come from and where poses go. Stages: body points -> features -> decoder (N samples batched)
-> FK anchored at the tracked head -> output.
"""
from dataclasses import dataclass

import numpy as np

from edge import quat
from edge.features import body_points, features, heading
from edge.inference import load_models
from edge.skeleton import HEAD, NUM_JOINTS, NUM_PREDICTED, fk


@dataclass
class Pose:
    """One output frame: world joint positions [J,3] (m), local joint rotations [J,3,3], foot contacts [2]."""
    positions: np.ndarray
    rotations: np.ndarray
    contacts: np.ndarray
    sample: int


class Pipeline:
    def __init__(self, models=None, samples=1, seed=0, fps=60.0, body_scale=1.0, precision="fp32", threads=1):
        if not 1 <= samples <= 128:
            raise ValueError(f"samples must be 1..128, got {samples}")
        self.manifest, self.decoder, self.autoencoder = load_models(models, samples, threads, precision)
        self.samples, self.fps, self.body_scale = samples, fps, body_scale
        self.threshold = self.manifest["plausibility_threshold_m"]
        # N=1 is the plain CVAE at the prior mean; more samples draw fixed latents once (SSI 3.2).
        rng = np.random.default_rng(seed)
        if samples > 1:
            self.decoder.latent[:] = rng.standard_normal(self.decoder.latent.shape).astype(np.float32)
        self.current = 0
        self._local = np.zeros((samples, NUM_JOINTS, 3, 3))
        self._prev_points = None

    def reset(self):
        self.decoder.reset()
        self._prev_points = None

    def step(self, sig):
        """sig: Signals for one frame (T=1). Returns the Pose for this frame."""
        points, waist_rot = body_points(sig, self.body_scale)
        points, waist_rot = points[0], waist_rot[0]
        prev = points if self._prev_points is None else self._prev_points
        yaw_q = heading(waist_rot)
        self.decoder.features[:] = features(points, prev, yaw_q, self.fps)
        self._prev_points = points
        self.decoder.step()

        # FK for every sample: root rotation is the waist IMU's, then hang the body from the tracked head.
        self._local[:, 0] = quat.to_matrix(waist_rot)
        quat.matrix_from_6d(self.decoder.rot6d.reshape(self.samples, NUM_PREDICTED, 6), out=self._local[:, 1:])
        _, pos = fk(self._local, np.zeros(3))
        pos += points[0] - pos[:, HEAD:HEAD + 1]
        c = self.current
        return Pose(pos[c], self._local[c].copy(), self.decoder.contacts[c].copy(), c)
