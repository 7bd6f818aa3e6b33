"""The `edge` command: one subcommand a tool, composed here, above every package it dispatches to
(the tools below it import none of each other: pyproject.toml's import-linter layers).

Each subcommand is a parser (`_add_<name>`) and a runner (`_<name>`) that imports its tool lazily,
so one subcommand loads only what it needs.
"""
import argparse
import sys
from pathlib import Path

from edge.inference import DEFAULT_PRECISION
from edge.modelfiles import ModelError


def add_refine_flags(p, what="refine the shown sample's latent against the live constraints (edge.refine)"):
    p.add_argument("--refine", action="store_true", help=what)
    p.add_argument("--refine-steps", type=int, default=2, help="Gauss-Newton steps a frame (K)")
    p.add_argument("--refine-terms", default=None,
                   help="comma-separated terms (default targets,keep,floor,legs; also imus, imus-tilt)")


def _add_eval(sub):
    ev = sub.add_parser("eval", help="measure reconstruction quality on BVH clips or sample files")
    ev.add_argument("--data", nargs="+", required=True, help="BVH files, folders of them, or edgepose sample .npz files")
    ev.add_argument("--split", choices=("train", "val"), help="filter a folder by its MANIFEST.tsv")
    ev.add_argument("--people", choices=("unseen", "seen"), default=None,
                    help="only the clips of performers with no clip in train (unseen) or with some (seen); "
                         "by default all, reported in both parts")
    ev.add_argument("--samples", type=int, default=1, help="latent samples N (1 = plain CVAE at the prior mean)")
    ev.add_argument("--no-ssi", action="store_true", help="keep the starting sample for the whole clip")
    ev.add_argument("--precision", choices=("fp32", "int8"), default=DEFAULT_PRECISION)
    ev.add_argument("--max-frames", type=int, default=None, help="evaluate at most this many frames per clip")
    ev.add_argument("--max-clips", type=int, default=None, help="an even spread of this many clips (a quick look)")
    ev.add_argument("--bodies", help="also on other bodies: 'standard' (12: three statures by short, average and long "
                                     "legs, long and short arms, the canonical) or a JSON list of {name, height_m, legs, "
                                     "arms}; BVH clips only; adds `bodies` to the JSON")
    ev.add_argument("--body-known", action="store_true",
                    help="with --bodies: the runtime is told each body's legs, as a [body] leg_length_m in the "
                         "board's config tells it, and sends its poses on them (edge.proportions)")
    ev.add_argument("--body-measured", action="store_true",
                    help="with --bodies: the runtime is told the legs and arms edge calibrate measures of each body "
                         "(the T-pose and the hip hold, simulated with hand tremor), and each body's entry gets "
                         "limb_error_cm")
    ev.add_argument("--json", required=True, help="write the metrics here")
    ev.add_argument("--dump", help="write one .npz per clip (gt_pos, pred_pos) into this folder")
    ev.add_argument("--models", help="model folder (default: the shipped models/)")
    ev.add_argument("--seed", type=int, default=0)
    ev.add_argument("--no-ik", action="store_true", help="skip foot-contact and arm IK (the bare network)")
    ev.add_argument("--trackers", default="none",
                    help="extra IMUs worn besides the waist, synthesised from the clip with IMU noise: none (default), "
                         "all, or a list of chest,l_thigh,r_thigh,l_shin,r_shin,l_foot,r_foot")
    ev.add_argument("--faults", choices=("disconnect",), help="DragPoser's faulty-sensor protocol on the extra trackers")
    ev.add_argument("--no-segments", action="store_true",
                    help="leave the worn IMUs' segments to the decoder (by default each takes its IMU's rotation)")
    ev.add_argument("--lookahead", type=int, default=None, help="SSI look-ahead tau in frames (default 0: the newest frame, as the board sends it; 10 was the paper's, 167 ms behind at 60 Hz)")
    add_refine_flags(ev)
    ev.add_argument("--no-heading", action="store_true",
                    help="leave the extra IMUs' heading offset and drift uncorrected (edge.heading runs by default)")
    ev.add_argument("--report", help="also draw the report (PNGs, GIF, index.html) into this folder (needs the [viz] extra; "
                                     "dumps into REPORT/dump unless --dump is given)")


def _add_report(sub):
    rpt = sub.add_parser("report", help="pictures of a run: skeletons, animation, per-joint errors, SSI, latency, tracker health")
    rpt.add_argument("run", help="the JSON `edge eval --json` wrote")
    rpt.add_argument("--dump", help="the folder `edge eval --dump` wrote (skeletons, animation and SSI timeline need it)")
    rpt.add_argument("--out", required=True, help="write the PNGs, the GIF and index.html here")
    rpt.add_argument("--clip", help="clip to draw, by file name (default: the one with the largest MPJPE)")
    rpt.add_argument("--every", type=int, default=20, help="frames between skeleton-strip columns")
    rpt.add_argument("--strip-frames", type=int, default=6, help="columns in the skeleton strip")
    rpt.add_argument("--gif-seconds", type=float, default=5.0, help="length of the animation in seconds")


def _add_ssi_study(sub):
    st = sub.add_parser("ssi-study", help="SSI target hitting / collision avoidance against N (SSI Table 3)")
    st.add_argument("--data", nargs="+", required=True)
    st.add_argument("--task", choices=("high-kick", "low-kick", "avoid"), required=True)
    st.add_argument("--samples", default="1,10,100", help="comma-separated N values")
    st.add_argument("--runs", type=int, default=5, help="runs per N, each with its own latent seed")
    st.add_argument("--split", choices=("train", "val"))
    st.add_argument("--max-clips", type=int, default=None)
    st.add_argument("--models")
    st.add_argument("--json", required=True)
    add_refine_flags(st, "kicks: the targets also go to the refiner (edge.refine), as a headset's would")


def _add_run(sub):
    run = sub.add_parser("run", help="the board service: sources in, poses out, live status")
    run.add_argument("--config", required=True, help="TOML or JSON config (see firmware_bridge/config.py)")
    run.add_argument("--seconds", type=float, default=None, help="stop after this long (default: run until Ctrl-C)")
    run.add_argument("--json", help="write the run's counters and timings here at exit")


def _add_calibrate(sub):
    cal = sub.add_parser("calibrate", help="stand in a T-pose: store IMU mounting offsets and height scale")
    cal.add_argument("--config", required=True)
    cal.add_argument("--seconds", type=float, default=3.0)
    cal.add_argument("--out", default="calibration.json")
    cal.add_argument("--legs", action="store_true",
                     help="after the T-pose, hold the left controller against the bony point at the side of the left hip: "
                          "the legs' length (floor to hip joint), for legs long or short for your height")


def _add_listen(sub):
    li = sub.add_parser("listen", help="decode the board's pose stream on a serial port, with a status line")
    li.add_argument("port")
    li.add_argument("--baud", type=int, default=460800)
    li.add_argument("--seconds", type=float, default=None)
    li.add_argument("--record", help="also write every byte read to this file, as it came (for a bug report)")
    li.add_argument("--plot", action="store_true", help="show a live 3D stick figure in a window (needs a display and the [viz] extra)")


def _add_replay(sub):
    rp = sub.add_parser("replay", help="replay a session through simulated devices into the real service")
    rp.add_argument("source", help="a session recording (.npz), a BVH clip or a sample take")
    rp.add_argument("--json", help="also write every figure of the run here, for scripts (the summary is printed "
                                   "either way; with --report and no --json it goes to REPORT/replay.json)")
    rp.add_argument("--transport", default="serial,i2c,can", help="which transports carry the IMUs")
    rp.add_argument("--faults", default="clean", help="a profile (" + ", ".join(
        ["noise", "loss", "corrupt", "disconnect", "disconnect-waist", "hand-loss", "unplug", "i2c-errors", "slow-i2c", "can-busoff", "clock-jump", "unplug-foot",
         "slimevr-restart", "slimevr-flood"])
        + "), several joined by '+', or a JSON object")
    rp.add_argument("--speed", choices=("realtime", "max"), default="realtime")
    rp.add_argument("--samples", default="16", help="N, or auto (adaptive N up to 32)")
    rp.add_argument("--adaptive", action="store_true",
                    help="let the deadline watchdog lower and raise N, as edge run does (--samples is the most)")
    rp.add_argument("--lookahead", type=int, default=0, help="SSI look-ahead in frames (default 0: the board's)")
    rp.add_argument("--precision", choices=("fp32", "int8"), default=DEFAULT_PRECISION)
    rp.add_argument("--seconds", type=float, default=None)
    rp.add_argument("--trackers", default=None,
                    help="extra IMUs on the simulated hub and CAN besides the waist: none, all, or a list such as "
                         "l_shin,r_shin (default l_foot,r_foot: the CAN foot trackers; a recording keeps its own)")
    rp.add_argument("--bvh", help="record the output as BVH here")
    rp.add_argument("--pose-log", help="write the pose stream's bytes, as the host read them, to this file")
    rp.add_argument("--pose-port", metavar="PATH", help="also put the pose stream on a serial port at PATH (a pty), "
                                                        "for `edge listen PATH` against the simulated board")
    rp.add_argument("--vmc", metavar="HOST:PORT", help="also send the body over VMC (VSeeFace, Warudo, VNyan: port 39539)")
    rp.add_argument("--vrchat", metavar="HOST:PORT", help="also send VRChat OSC trackers (VRChat listens on port 9000)")
    rp.add_argument("--calibration", help="a calibration file (edge calibrate's): the outputs carry its body size")
    rp.add_argument("--models")
    rp.add_argument("--report", help="also draw the report (latency, tracker health) into this folder ([viz] extra)")


def _add_record(sub):
    rec = sub.add_parser("record", help="capture live traffic from the configured transports into a session file")
    rec.add_argument("--config", required=True)
    rec.add_argument("--seconds", type=float, default=10.0)
    rec.add_argument("--out", required=True)


def _add_profile(sub):
    pf = sub.add_parser("profile", help="how many SSI samples fit a CPU budget (real pipeline, real time, cgroup quota)")
    from edgetools import profile as profile_mod      # light import: no numpy or onnxruntime at module level
    profile_mod.add_arguments(pf)


def _add_soak(sub):
    sk = sub.add_parser("soak", help="hours of one board on every transport, faults mixed in: memory, descriptors, "
                                     "threads, late frames, recovery (issue #55)")
    sk.add_argument("--minutes", type=float, required=True, help="how long (a play session: 120)")
    sk.add_argument("--json", required=True, help="the summary (minutes, rss_growth_mb_per_h, fd_growth, ..., ok)")
    sk.add_argument("--lines", help="the samples as JSON lines (default: beside --json, .jsonl)")
    sk.add_argument("--plot", help="a PNG of the samples (needs the viz extra)")
    sk.add_argument("--source", nargs="+", help="BVH clips or sample takes, played in turn (default: the bundled walk)")
    sk.add_argument("--part-s", type=float, default=60.0, help="seconds of each part (one fault each)")
    sk.add_argument("--sample-s", type=float, default=60.0, help="seconds between samples (a multiple of --part-s)")
    sk.add_argument("--samples", default="16", help="SSI samples N, or auto (the governor, as the board runs)")
    sk.add_argument("--precision", default=DEFAULT_PRECISION, choices=("int8", "fp32"))


def _soak(args):
    if args.plot:
        from viz.canvas import require_plotting
        require_plotting()                   # say what to install before soaking, not after
    from edgetools.sim import soak
    code = soak.main(args)
    if args.plot and code in (0, 1):
        import json
        from viz.figures import soak_figure
        summary = json.loads(Path(args.json).read_text())
        rows = [json.loads(line) for line in Path(summary["lines"]).read_text().splitlines()]
        soak_figure(rows, summary, args.plot)
        print(f"wrote {args.plot}")
    return code


def _eval(args):
    from edgetools import eval as ev_mod
    if args.report:
        from viz.canvas import require_plotting
        require_plotting()                   # say what to install before evaluating, not after
        args.dump = args.dump or str(Path(args.report) / "dump")
    code = ev_mod.main(args)
    if code == 0 and args.report:
        from viz.report import build_report
        print(f"wrote {build_report(args.json, args.report, args.dump)}")
    return code


def _report(args):
    from viz import report
    return report.main(args)


def _run(args):
    from firmware_bridge import commands
    return commands.run(args)


def _calibrate(args):
    from firmware_bridge import commands
    return commands.calibrate(args)


def _profile(args):
    from edgetools import profile
    return profile.main(args)


def _record(args):
    from edgetools.sim import record
    return record.main(args)


def _replay(args):
    from edgetools.sim import replay_cli
    if args.report:
        from viz.canvas import require_plotting
        require_plotting()                   # say what to install before replaying, not after
        args.json = args.json or str(Path(args.report) / "replay.json")     # the report draws from it
    code = replay_cli.main(args)
    if code == 0 and args.report:
        from viz.report import build_report
        dump = Path(args.report) / "dump"
        print(f"wrote {build_report(args.json, args.report, dump if any(dump.glob('*.npz')) else None)}")
    return code


LISTEN_STATUS_HZ = 4       # status-line redraws a second under --plot when there is no window


def listen_plot_loop(listener, seconds=None):
    """`edge listen --plot`'s loop: viz.live's window on the listener, or, without a display, the
    listener's own status line (edgetools.listen.status_loop)."""
    from edgetools.listen import status_loop
    from viz.live import live_plot

    def fallback(ear, secs):
        return status_loop(ear, secs, every=1.0 / LISTEN_STATUS_HZ)

    return live_plot(listener, seconds, fallback=fallback)


def _listen(args):
    from edgetools import listen
    return listen.main(args, loop=listen_plot_loop if args.plot else None)


def _ssi_study(args):
    from edgetools import study
    return study.main(args)


COMMANDS = {"eval": (_add_eval, _eval), "report": (_add_report, _report), "ssi-study": (_add_ssi_study, _ssi_study),
            "run": (_add_run, _run), "calibrate": (_add_calibrate, _calibrate), "listen": (_add_listen, _listen),
            "replay": (_add_replay, _replay), "record": (_add_record, _record), "profile": (_add_profile, _profile),
            "soak": (_add_soak, _soak)}


def main(argv=None):
    ap = argparse.ArgumentParser(prog="edge", description="edgepose: full-body pose from a headset, controllers and IMU trackers")
    sub = ap.add_subparsers(dest="cmd", required=True)
    for add, _ in COMMANDS.values():
        add(sub)
    args = ap.parse_args(argv)
    try:
        return COMMANDS[args.cmd][1](args)
    except ModelError as e:
        print(f"edge: {e}", file=sys.stderr)
        return 2
