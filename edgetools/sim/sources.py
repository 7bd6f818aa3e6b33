"""What `edge replay` plays: a recorded session as recorded, or a take or BVH clip synthesised through
the device models (tiled to the length asked for)."""
import sys

import numpy as np

from edgetools.sim.session import FAULTS, Session, synthesize


def tile_take(take, seconds):
    """Repeat a take until it lasts `seconds` (for soaks); the body jumps back at each seam."""
    from edge.signals import Signals
    reps = int(np.ceil(seconds * take.fps / take.frames))
    if reps <= 1:
        return take
    sig = take.signals
    from dataclasses import fields
    tiled = Signals(**{f.name: np.concatenate([getattr(sig, f.name)] * reps) for f in fields(sig)})
    imu = {k: np.concatenate([v] * reps) for k, v in (take.imu or {}).items()}
    return type(take)(take.name, tiled, np.concatenate([take.gt_pos] * reps), take.fps, imu)


# Faults the simulated devices apply while replaying; the others shape the traffic when a session is
# synthesised from a take, so a recording cannot have them.
REPLAY_TIME_FAULTS = {"unplug_at", "unplug_s", "i2c_error_rate", "i2c_block_ms", "i2c_block_every_ms"}


def load_source(source, transports, faults, seed=0, seconds=None, trackers=None):
    """A recording (.npz session), or a BVH clip / sample take synthesised through the device models
    (repeated to last `seconds` when that is longer than the take) with the extra IMUs `trackers`
    (default: the two CAN foot trackers). A recording carries the trackers it was made with."""
    path = str(source)
    if path.endswith(".npz"):
        d = np.load(path, allow_pickle=False)
        if "kind" in d.files:
            ignored = sorted(set(faults or {}) - REPLAY_TIME_FAULTS)
            if ignored:
                profiles = sorted({name for name, params in FAULTS.items() if set(params) & set(ignored)})
                take = path.replace(".session.npz", ".npz") if path.endswith(".session.npz") else "a take or BVH clip"
                print(f"edge replay: {path} is a recording, replayed as recorded: the fault profile(s) "
                      f"{', '.join(profiles) or ', '.join(ignored)} shape traffic as it is synthesised and do not apply "
                      f"to it (unplug and i2c-errors do). To inject them, replay {take}", file=sys.stderr)
            session = Session.load(path)
            if trackers is not None and tuple(trackers) != tuple(session.meta.get("trackers", ["waist"])[1:]):
                print(f"edge replay: {path} is a recording made with trackers "
                      f"{','.join(session.meta.get('trackers', ['waist']))}; --trackers applies to a take or BVH clip "
                      f"(e.g. samples/cmu_09_12_walk.npz)", file=sys.stderr)
            return session
    from motion.takes import load_take
    take = load_take(path)
    if seconds:
        take = tile_take(take, seconds)
    return synthesize(take, transports, faults, seed, trackers=trackers)
