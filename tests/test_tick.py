"""The board tick outside the pipeline (#32 item 5): the poll, the synchroniser and the pose stream's
encoding allocate no arrays tick after tick, and the compiled pose encoder writes the reference's bytes."""
import tracemalloc

import numpy as np
import pytest

from edge import native, quat
from firmware_bridge.wire import messages

TICKS = 2000
# A tick part's transient peak of traced memory: what the Python bindings make per call (ctypes'
# argument objects, a memoryview, floats) stays under this; one numpy array of a pose's quaternions
# is 0.8 KB on its own, and the numpy synchroniser and encoder this replaced peaked at 1.7-4.7 KB.
PEAK_BYTES = 1200


# The canonical body, and a user whose legs are long for their height: every pose then goes through
# edge.proportions.UserBody on its way out.
@pytest.fixture(scope="module", params=[None, {"height_m": 1.62, "leg_length_m": 0.86}], ids=["canonical", "user"])
def service(request):
    from edgetools.profile import Feeder, board_service
    feeder = Feeder(60.0, "tick-memory")
    svc = board_service({"hz": 60.0, "precision": "int8", "refine_steps": 0, "body": request.param}, 4, feeder, 0)
    assert svc.outputs.body.canonical == (request.param is None)
    for k in range(700):            # past the frame-time ring (600) and every stream's ring
        svc.step(feeder.frame(k))
    yield svc, feeder
    svc.close()
    feeder.close()


def peak_of(fn):
    before = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    out = fn()
    return out, tracemalloc.get_traced_memory()[1] - before


@pytest.mark.skipif(not native.load(), reason="the board's tick encodes with the compiled core")
def test_poll_sync_and_the_pose_stream_allocate_no_arrays_tick_after_tick(service):
    svc, feeder = service
    peaks = {part: np.zeros(TICKS) for part in ("poll", "sync", "emit")}     # made before tracing starts
    tracemalloc.start()
    try:
        start = tracemalloc.get_traced_memory()[0]
        halfway = None
        for i in range(TICKS):
            if i == TICKS // 2:
                halfway = tracemalloc.get_traced_memory()[0] - start
            now = feeder.frame(700 + i)
            peaks["poll"][i] = peak_of(svc.poll)[1]
            (sig, health), peaks["sync"][i] = peak_of(lambda now=now: svc.sync.frame(now, svc._frame))
            pose = svc.pipeline.step(svc.calibrated(sig))
            peaks["emit"][i] = peak_of(lambda pose=pose, health=health: svc.latency.pose(
                health.newest_rx, svc.outputs.send(pose, health, svc.pipeline.t, svc.pipeline.samples)))[1]
            svc.latency.frame(0.0)              # as tick() does, so the ring stays full
        growth = tracemalloc.get_traced_memory()[0] - start
    finally:
        tracemalloc.stop()
    worst = {part: int(v.max()) for part, v in peaks.items()}
    assert all(p < PEAK_BYTES for p in worst.values()), worst
    # Nothing kept per tick: Python's int and float free lists shift some KB around in the first
    # thousand ticks (9-22 KB, depending on what ran before in the process), and then hold; one float
    # kept a tick would add 24 KB a thousand ticks.
    assert halfway < 32_768 and growth - halfway < 8_192, (halfway, growth)


@pytest.mark.skipif(not native.load(), reason="the compiled core is what PoseEncoder runs")
def test_the_compiled_pose_encoder_writes_the_references_bytes_and_refuses_what_it_refuses():
    enc, rng = messages.PoseEncoder(), np.random.default_rng(7)
    reused = messages.PoseFrame(0.0, np.zeros(3), np.zeros((21, 4)), np.zeros(2))

    def encoded(fn):
        try:
            return bytes(fn())
        except ValueError as e:
            return str(e)
    refused = 0
    for i in range(3000):
        q = rng.normal(size=(21, 4)) * 10 ** rng.uniform(-3, 3, size=(21, 1))
        if i % 3 == 0:
            q = quat.normalize(q)
        if i % 11 == 0:
            q[5] = np.round(q[0] * 4) / 4                        # exact halves: numpy rounds them to even
        if i % 19 == 0:
            q[3] = [np.nan, 0, 0, 1] if i % 2 else [0, 0, 0, 0]
        root = rng.uniform(-40, 40, 3) if i % 5 == 0 else np.round(rng.uniform(-3, 3, 3) * 2000) / 2000
        if i % 23 == 0:
            root[1] = np.inf
        frame = reused if i % 2 else messages.PoseFrame(0.0, np.zeros(3), np.zeros((21, 4)), np.zeros(2))
        frame.rotations[:], frame.root_pos[:], frame.contacts[:] = q, root, rng.uniform(-0.5, 1.5, 2)
        frame.t, frame.num_samples = rng.uniform(0, 5000), int(rng.integers(256))
        frame.ssi_flags, frame.trackers_lost = int(rng.integers(256)), int(rng.integers(65536))
        seq = int(rng.integers(1 << 20))
        want = encoded(lambda frame=frame, seq=seq: messages.encode_pose_frame(frame, seq))
        assert encoded(lambda frame=frame, seq=seq: enc.encode(frame, seq)) == want, i
        refused += isinstance(want, str)
    assert 100 < refused < 1000             # both sides of the checks were exercised
