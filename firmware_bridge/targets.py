"""Targets from the headset (protocol.md section 4.1) to the refiner: a hand to reach, a foot to plant.

The headset speaks in the user's space and seconds; the refiner works on the canonical body in model
frames, so each target is scaled by the calibration's height scale and its window counted in ticks."""
import numpy as np


class TargetInbox:
    def __init__(self, pipeline, height_scale, hz):
        self.pipeline, self.height_scale, self.hz = pipeline, height_scale, hz
        self.counts = {"targets_in": 0, "targets_ignored": 0}

    def add(self, s):
        """A TARGET sample: to the refiner, its window from the next tick; refused with a reason there
        (edge.refine: non-finite, unknown joint, beyond reach of the pelvis; counted by reason), or
        ignored (counted) when refinement or its targets are off. A clear removes the target."""
        self.counts["targets_in"] += 1
        if not self.pipeline.takes_targets:
            self.counts["targets_ignored"] += 1
            return
        if s.clear:
            self.pipeline.remove_target(s.target_id)
            return
        scale = self.height_scale
        self.pipeline.add_target(s.joint, np.asarray(s.position, dtype=np.float64) * scale, s.radius * scale,
                                 start=round(s.start * self.hz), frames=round(s.duration * self.hz), key=s.target_id)
