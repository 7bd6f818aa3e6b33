"""One side of `bench/tick.py`: the board service of whichever tree is first on PYTHONPATH, fed one
headset and one waist sample a tick in-process (edgetools.profile's Feeder, as `edge profile` does),
timed part by part on request.

    PYTHONPATH=TREE python bench/tick_worker.py N PRECISION WARMUP

Prints {"ready": true} after WARMUP ticks; then each stdin line 'tick K' runs K more ticks and answers
with one JSON object of per-tick durations in microseconds: poll (the sources' samples into the
synchroniser), sync (the synchroniser's frame), step (Pipeline.step), emit (the pose encoded and sent,
the age recorded) and tick (Service.step whole: the four and the counters around them). Imports only
what both this tree and older ones have (edgetools.profile.Feeder and board_service, Service.poll,
Service.tick and its tick_marks).
"""
import json
import sys
import time


def main():
    n, precision, warmup = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
    from edgetools.profile import Feeder, board_service
    cfg = {"hz": 60.0, "precision": precision, "refine_steps": 0}
    feeder = Feeder(cfg["hz"], f"tick{n}")
    service = board_service(cfg, n, feeder, 0)
    marks, clock = service.tick_marks, time.perf_counter_ns
    k = 0
    for k in range(warmup):
        service.step(feeder.frame(k))
    print(json.dumps({"ready": True}), flush=True)
    for line in sys.stdin:
        count = int(line.split()[1])
        out = {part: [0.0] * count for part in ("poll", "sync", "step", "emit", "tick")}
        for i in range(count):
            k += 1
            now = feeder.frame(k)
            t0 = clock()
            service.poll()
            t1 = clock()
            service.tick(now)
            t2 = clock()
            out["poll"][i] = (t1 - t0) / 1000.0
            out["sync"][i] = (marks[1] - marks[0]) * 1e6
            out["step"][i] = (marks[2] - marks[1]) * 1e6
            out["emit"][i] = (marks[3] - marks[2]) * 1e6
            out["tick"][i] = (t2 - t0) / 1000.0
        print(json.dumps(out), flush=True)
    service.close()
    feeder.close()


if __name__ == "__main__":
    main()
