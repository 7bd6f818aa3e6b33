"""Round trip and lag of the WebXR headset link on loopback: page -> board -> page.

    python bench/webxr_roundtrip.py [--seconds 10] [--samples 8] [--lookahead 0] [--screenshot docs/img/webxr_mirror.png]

The board's `edge run` Service with a webxr:// headset on 127.0.0.1 (TLS) and the emulated Meta Quest 3
(edgetools.sim.quest: the board's page in headless Chromium with iwer, playing the bundled walk at 72 Hz).
Each body the board returns carries the page time it stands for: the newest headset pose the board had
when it sent it, less any SSI look-ahead the frame was held for; the page records `performance.now()`
minus that for every body, the lag its panel shows. That is: the headset pose over the socket, waiting
for the next 60 Hz model tick, the tick (synchroniser, model, encoding), the look-ahead (none by
default), the body back over the socket and its decoding in the page.

Prints the page's lag p50 / p99, the board's own pose age and motion-to-pose lag (firmware_bridge.service:
from the newest sample a tick used reaching the board to the pose leaving it, plus the look-ahead), the
clock pings' round trip (the socket alone, measured by the board) and the board's frame time, all
measured in this run. Needs Chromium, node's iwer and Playwright
(as tests/test_webxr_browser.py does).
"""
import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from edgetools.sim.quest import EmulatedQuest
from motion.takes import from_sample
from firmware_bridge import config as config_mod
from firmware_bridge.service import Service

SAMPLE = Path(__file__).resolve().parent.parent / "samples" / "cmu_09_12_walk.npz"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--lookahead", type=int, default=0, help="SSI look-ahead in frames (default 0, the board's)")
    ap.add_argument("--screenshot", help="save the page's view (the mirrored body) here at the end")
    args = ap.parse_args(argv)
    missing = EmulatedQuest.missing()
    if missing:
        print(f"webxr_roundtrip: {missing}", file=sys.stderr)
        return 2
    state = tempfile.mkdtemp(prefix="edgepose-webxr-")
    cfg = config_mod.from_dict({"headset": {"url": f"webxr://127.0.0.1:0?state={state}"},
                                "runtime": {"samples": args.samples, "adaptive": False,
                                                                "lookahead": args.lookahead}}, "bench")
    service = Service(cfg, status=None)
    source = service.headset.source
    stop = threading.Event()
    runner = threading.Thread(target=service.run, kwargs={"stop": stop.is_set}, daemon=True)
    runner.start()
    quest = EmulatedQuest(from_sample(SAMPLE))
    pings = []
    try:
        quest.open(source.page_urls()[0])
        quest.pair(source.code)
        quest.wait("window.edgepose.paired")
        time.sleep(0.5)
        quest.play(quest.page_now_ms())
        quest.enter()
        quest.wait("window.edgepose.bodies > 60")           # the first second: warm-up, not measured
        first = quest.page.evaluate("window.edgepose.roundTripCount")
        time.sleep(args.seconds)
        headset = source._headset
        if headset is not None:                              # the pings of the measured span (one per 0.5 s)
            pings = list(headset.clock.rtt)[-int(args.seconds / 0.5):]
        trips = quest.page.evaluate(f"""(() => {{ const s = window.edgepose; const out = [];
            for (let k = {first}; k < s.roundTripCount; k++) out.push(s.roundTrips[k % 4096]); return out; }})()""")
        page = quest.state()
        if args.screenshot:
            Path(args.screenshot).parent.mkdir(parents=True, exist_ok=True)
            quest.page.screenshot(path=args.screenshot)
    finally:
        quest.close()
        stop.set()
        runner.join(5)
    summary = service.summary()
    trips = np.array(trips[-4096:])
    pings = np.array(pings) if pings else np.zeros(1)
    print(f"webxr lag on loopback, page -> board -> page, {len(trips)} bodies over {args.seconds:.0f} s "
          f"(N={args.samples}, look-ahead {args.lookahead} frames, 72 Hz headset, 60 Hz model):")
    print(f"  page's lag       p50 {np.percentile(trips, 50):6.2f} ms   p99 {np.percentile(trips, 99):6.2f} ms   "
          f"max {trips.max():6.2f} ms   (what its panel shows)")
    age, lag = summary["pose_age_ms"], summary["motion_to_pose_lag_ms"]
    print(f"  board pose age   p50 {age['p50']:6.2f} ms   p99 {age['p99']:6.2f} ms")
    print(f"  board lag        p50 {lag['p50']:6.2f} ms   p99 {lag['p99']:6.2f} ms   (pose age + look-ahead)")
    print(f"  socket alone     p50 {np.percentile(pings, 50):6.2f} ms   p99 {np.percentile(pings, 99):6.2f} ms   "
          f"(the board's clock pings)")
    print(f"  board frame      p50 {summary['frame_ms']['p50']:6.2f} ms   p99 {summary['frame_ms']['p99']:6.2f} ms")
    print(f"  page: {page['sent']} poses sent, {page['skipped']} skipped, {page['bodies']} bodies, "
          f"{page['drawn']} frames drawn; board: {summary['frames_in']} ticks with input, "
          f"{summary['deadline_misses']} late")
    return 0


if __name__ == "__main__":
    sys.exit(main())
