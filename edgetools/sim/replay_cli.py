"""`edge replay`'s command: parse the source and the fault profile, replay, write the JSON, say the numbers."""
import json
import os
import sys
from pathlib import Path

from edgetools.sim.devices import close_pty_at, open_pty_at
from edgetools.sim.replay import replay
from firmware_bridge.transports import TransportError
from edgetools.sim.session import fault_profile
from edgetools.sim.sources import load_source


class PosePort:
    """A serial port a host program can open (a pty's slave end, behind the symlink `path`) that carries
    the replayed board's pose stream: `edge listen PATH` against a simulated board. Bytes nobody reads
    are dropped, as a UART would lose them."""

    def __init__(self, path):
        self.path = str(path)
        self.master, self.slave = open_pty_at(self.path)
        os.set_blocking(self.master, False)

    def write(self, data):
        try:
            os.write(self.master, data)
        except OSError:
            pass

    def close(self):
        close_pty_at(self.path, self.master, self.slave)


class Tee:
    """write() to every sink."""

    def __init__(self, sinks):
        self.sinks = sinks

    def write(self, data):
        for sink in self.sinks:
            sink.write(data)


def main(args):
    try:
        faults = fault_profile(args.faults)
    except ValueError as e:
        print(f"edge replay: {e}", file=sys.stderr)
        return 2
    transports = tuple(args.transport.split(","))
    bad = set(transports) - {"serial", "i2c", "can", "slimevr"}
    if bad:
        print(f"edge replay: unknown transport {sorted(bad)[0]!r}; use serial, i2c, can, slimevr", file=sys.stderr)
        return 2
    try:
        from edge.imus import parse_set
        trackers = None if args.trackers is None else parse_set(args.trackers)
        session = load_source(args.source, transports, faults, seconds=args.seconds, trackers=trackers)
    except (OSError, ValueError) as e:
        print(f"edge replay: cannot use {args.source}: {e}", file=sys.stderr)
        return 2
    samples = 32 if args.samples == "auto" else int(args.samples)
    sinks = []                  # where the pose stream's bytes go besides the replay's own reader
    if getattr(args, "pose_log", None):
        sinks.append(open(args.pose_log, "wb"))
    if getattr(args, "pose_port", None):
        sinks.append(PosePort(args.pose_port))
        print(f"edge replay: the pose stream is on {args.pose_port}; read it with: edge listen {args.pose_port}",
              file=sys.stderr)
    pose_log = Tee(sinks) if sinks else None
    try:
        runtime = {"samples": samples, "lookahead": args.lookahead, "precision": args.precision, "models": args.models,
                   "adaptive": args.adaptive or args.samples == "auto",
                   "calibration": getattr(args, "calibration", None)}
        output = {"bvh": args.bvh, "vmc": getattr(args, "vmc", None), "vrchat": getattr(args, "vrchat", None)}
        result = replay(session, args.speed, args.seconds, runtime=runtime, output=output, faults=faults,
                        status=sys.stderr, pose_log=pose_log,
                        dump=str(Path(args.report) / "dump") if getattr(args, "report", None) else None)
    except (ValueError, TransportError) as e:     # a bad --vmc / --vrchat address or calibration file
        print(f"edge replay: {e}", file=sys.stderr)
        return 2
    finally:
        for sink in sinks:
            sink.close()
    written = [path for path in (args.json, args.bvh) if path]
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    keys = ("frames_in", "frames_out", "poses_decoded", "packets_corrupt", "packets_lost", "tracker_lost_events",
            "deadline_misses", "ssi_switches", "mpjpe_cm", "jitter_m_s3")
    print("\n" + "  ".join(f"{k}={result[k]:.4g}" if isinstance(result.get(k), float) else f"{k}={result.get(k)}"
                           for k in keys), file=sys.stderr)
    lag, age = result["motion_to_pose_lag_ms"], result["pose_age_ms"]
    print(f"motion-to-pose lag p50 {lag['p50']:.1f} ms p99 {lag['p99']:.1f} ms (pose age p99 {age['p99']:.1f} ms + "
          f"look-ahead {result['lookahead_ms']:.0f} ms); host latency p50 {result['latency_ms']['p50']:.2f} ms "
          f"p99 {result['latency_ms']['p99']:.2f} ms" + (f"; wrote {' and '.join(written)}" if written else ""),
          file=sys.stderr)
    if result["errors"]:        # the run went on, but something broke: say so in the exit code
        print(f"edge replay: {len(result['errors'])} error(s), the first: {result['errors'][0]}", file=sys.stderr)
        return 1
    return 0
