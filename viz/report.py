"""`edge report RUN.json [--dump DIR] --out DIR`: the pictures of a run and an index.html that shows them.

RUN.json is what `edge eval --json` (or `edge replay`, `edge profile`) wrote; DIR the folder
`edge eval --dump` wrote (one .npz per clip).
What gets drawn depends on what the data carries; every picture that cannot be drawn gets a line in
index.html saying why:

    skeleton strip, animation   need --dump (gt_pos, pred_pos per frame)
    per-joint errors            RUN.json: per_joint_mpjpe_cm and joint_names
    SSI timeline                --dump from a run with --samples N > 1 (cost, sample, transition, switches)
    latency histogram           RUN.json: latency_ms_samples, a list of per-frame latencies in ms
                                (edge eval measures quality, not time; the simulator will add them)
    tracker health              RUN.json: health_timeline (format: viz.figures.check_health_timeline)
    adaptive N under contention RUN.json from `edge profile --hog-at S` / `--adaptive`: contention
                                (frame_ms_per_frame, samples_timeline, hog)

Skeletons, the animation and the SSI timeline are drawn for one clip: --clip NAME, or by default the
clip with the largest MPJPE in RUN.json.
"""
import html
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from viz import canvas

STRIP_EVERY = 20           # frames between strip columns (1/3 s at 60 fps)
STRIP_FRAMES = 6
GIF_SECONDS = 5.0
GIF_FPS = 20
SSI_KEYS = ("cost", "sample", "transition", "switches", "threshold")
METRICS = (("clips", "clips", "{}"), ("frames", "frames scored", "{}"), ("samples", "latent samples N", "{}"),
           ("mpjpe_cm", "MPJPE", "{:.2f} cm"), ("mpjve_cm_s", "velocity error", "{:.1f} cm/s"),
           ("jitter_m_s3", "jitter", "{:.0f} m/s³"), ("ee_error_cm", "end-effector error", "{:.2f} cm"),
           ("foot_skate_cm_s", "foot skate", "{:.1f} cm/s"), ("implausible_rate", "implausible frames", "{:.1%}"),
           ("ssi_switches", "SSI switches", "{}"))


@dataclass
class Section:
    """One entry of index.html: a picture with its caption, or the reason there is none."""
    title: str
    image: str | None
    text: str


def main(args):
    try:
        index = build_report(args.run, args.out, args.dump, args.clip, args.every, args.strip_frames, args.gif_seconds)
    except (FileNotFoundError, ValueError) as e:
        print(f"edge report: {e}", file=sys.stderr)
        return 2
    print(f"wrote {index}")
    return 0


def build_report(run_json, out, dump=None, clip=None, every=STRIP_EVERY, strip_frames=STRIP_FRAMES,
                 gif_seconds=GIF_SECONDS):
    """Draw everything the run's data allows into `out`; returns the path of index.html."""
    canvas.require_plotting()
    if not Path(run_json).is_file():
        raise FileNotFoundError(f"no such file: {run_json} (write it with edge eval --json)")
    run = json.loads(Path(run_json).read_text())
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sections = []
    if dump:
        path = choose_clip(dump, run, clip)
        data = dict(np.load(path))
        sections += clip_sections(data, path.stem, out, every, strip_frames, gif_seconds)
    else:
        sections.append(Section("Skeletons and SSI", None, "Skipped: no --dump folder given. Skeleton strip, "
                                "animation and SSI timeline need the per-frame poses `edge eval --dump DIR` writes."))
    sections.append(per_joint_section(run, out))
    sections.append(latency_section(run, out))
    sections.append(health_section(run, out))
    sections.append(contention_section(run, out))
    return write_index(out, Path(run_json), run, sections)


# --------------------------------------------------------------------------------------------------
# Which clip


def choose_clip(dump, run, name=None):
    """The dump file to draw: the one named, or the clip with the largest MPJPE in the run."""
    files = sorted(Path(dump).glob("*.npz"))
    if not files:
        raise FileNotFoundError(f"no .npz files in {dump} (write them with edge eval --dump {dump})")
    by_stem = {f.stem: f for f in files}
    if name:
        stem = Path(name).name.removesuffix(".npz").removesuffix(".bvh")
        if stem not in by_stem:
            raise ValueError(f"no clip {name!r} in {dump}; there are: {', '.join(list(by_stem)[:10])}"
                             + (" ..." if len(by_stem) > 10 else ""))
        return by_stem[stem]
    scored = [(c["mpjpe_cm"], Path(c["clip"]).stem) for c in run.get("per_clip", []) if Path(c["clip"]).stem in by_stem]
    return by_stem[max(scored)[1]] if scored else files[0]


# --------------------------------------------------------------------------------------------------
# Sections


def clip_sections(d, clip, out, every, strip_frames, gif_seconds):
    """Skeleton strip, animation and SSI timeline of one dumped clip."""
    from viz.animation import skeleton_gif
    from viz.figures import skeleton_strip

    gt, pred, fps = d["gt_pos"], d["pred_pos"], float(d["fps"])
    names, parents = [str(n) for n in d["joint_names"]], d["parents"]
    T = len(gt)
    start = min(int(d.get("warmup_frames", 0)), T - 1)
    strip = np.arange(start, T, max(1, every))[:strip_frames]
    skeleton_strip(gt, pred, parents, names, fps, strip, out / "skeleton_strip.png",
                   title=f"{clip}: every {every} frames ({every / fps:.2f} s) from {start / fps:.1f} s")
    step = max(1, round(fps / GIF_FPS))
    moving = np.arange(start, min(T, start + int(gif_seconds * fps)), step)
    skeleton_gif(gt, pred, parents, names, fps, moving, out / "animation.gif", out_fps=fps / step, title=clip)
    sections = [
        Section("Skeleton strip", "skeleton_strip.png",
                f"Clip {clip}, {len(strip)} frames {every / fps:.2f} s apart, after the {start / fps:.1f} s warm-up. "
                "Front and side views turn with the ground-truth body; the number under each prediction column is "
                "that frame's mean joint error."),
        Section("Animation", "animation.gif",
                f"Clip {clip}, {len(moving) * step / fps:.1f} s at {fps / step:.0f} frames per second (real time): "
                "ground truth on the left, prediction on the right.")]
    return sections + [ssi_section(d, clip, out)]


def ssi_section(d, clip, out):
    from viz.figures import ssi_timeline

    missing = [k for k in SSI_KEYS if k not in d]
    if missing:
        return Section("SSI timeline", None, f"Skipped: the dump has no {', '.join(missing)} "
                       "(written by edge eval --dump since SSI dumps were added; re-run the evaluation).")
    if d["cost"].shape[1] < 2:
        return Section("SSI timeline", None, "Skipped: the run used one latent sample (N = 1), so there was nothing "
                       "to select between. Evaluate with --samples 8 to see SSI at work.")
    fps = float(d["fps"])
    ssi_timeline(d["cost"], d["sample"].astype(int), d["transition"].astype(bool), d["switches"],
                 float(d["threshold"]), fps, int(d.get("warmup_frames", 0)), out / "ssi_timeline.png",
                 title=f"SSI sample selection, {clip}, N = {d['cost'].shape[1]}")
    return Section("SSI timeline", "ssi_timeline.png",
                   f"Each of the {d['cost'].shape[1]} samples' selection cost when its frame was judged (lower-body "
                   "autoencoder error), the sample shown, and the outlier bound: the shown sample's cost rising "
                   "above it triggers a switch (vertical lines). The transition to the new sample (shaded) starts "
                   "at the oldest frame not yet sent, the look-ahead before the detection.")


def per_joint_section(run, out):
    from viz.figures import per_joint_errors

    errors, names = run.get("per_joint_mpjpe_cm"), run.get("joint_names")
    if not errors or not names or len(errors) != len(names):
        return Section("Per-joint error", None,
                       "Skipped: RUN.json has no per_joint_mpjpe_cm with matching joint_names.")
    per_joint_errors(errors, names, out / "per_joint_error.png",
                     title=f"Per-joint position error: {run.get('clips', '?')} clip(s), "
                           f"{run.get('frames', '?')} frames, N = {run.get('samples', '?')}")
    return Section("Per-joint error", "per_joint_error.png",
                   "Mean distance between predicted and true joint positions over the scored frames. The head and "
                   "wrists are pinned to the headset and controllers, so their error is zero.")


def latency_section(run, out):
    from viz.figures import FRAME_BUDGET_MS, latency_histogram

    samples = run.get("latency_ms_samples")
    if samples is None:
        return Section("Latency", None, "Skipped: RUN.json has no latency_ms_samples. edge eval measures quality, not "
                       "time; runs of the hardware-in-the-loop simulator will carry per-frame latencies.")
    lat = np.asarray(samples, dtype=float)
    if lat.ndim != 1 or len(lat) == 0 or not np.all(np.isfinite(lat)):
        return Section("Latency", None, "Skipped: latency_ms_samples must be a non-empty list of finite numbers (ms).")
    latency_histogram(lat, out / "latency.png")
    return Section("Latency", "latency.png",
                   f"Per-frame latency of {len(lat)} frames against the {FRAME_BUDGET_MS:.1f} ms budget "
                   "of a 60 Hz frame.")


def health_section(run, out):
    from viz.figures import health_timeline

    health = run.get("health_timeline")
    if health is None:
        return Section("Tracker health", None, "Skipped: RUN.json has no health_timeline (lost trackers, corrupt "
                       "packets, injected faults per frame); runs of the simulator will carry one.")
    try:
        health_timeline(health, out / "health_timeline.png")
    except ValueError as e:
        return Section("Tracker health", None, f"Skipped: {e}.")
    return Section("Tracker health", "health_timeline.png",
                   "Red: a tracker was lost (no data for 250 ms); green triangles: it came back. Grey ticks: corrupt "
                   "packets. Purple dashed lines: faults the simulator injected.")


def contention_section(run, out):
    from viz.figures import contention_timeline

    c = run.get("contention") or {}
    ms, steps = c.get("frame_ms_per_frame"), c.get("samples_timeline")
    if not ms or not steps:
        return Section("Adaptive N under contention", None, "Skipped: only `edge profile --hog-at S` or "
                       "`--adaptive` runs carry per-frame times and the N timeline.")
    title = ("Adaptive N" if run.get("adaptive") else "Fixed N") + (" under a CPU hog" if c.get("hog") else "")
    contention_timeline(ms, steps, c.get("period_ms", 1000.0 / 60.0), c.get("hog"), out / "contention.png", title)
    phases = c.get("phases", {})
    text = "; ".join(f"{k}: {v['deadline_misses']} late of {v['frames']} frames, N mean {v['samples_mean']:g}"
                     for k, v in phases.items() if k != "whole")
    return Section("Adaptive N under contention", "contention.png",
                   f"Each frame's response time (release to done) and the number of samples running. {text}.")


# --------------------------------------------------------------------------------------------------
# index.html

PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{title}</title>
<style>
  body {{ font-family: system-ui, sans-serif; margin: 2rem auto; max-width: 1500px; padding: 0 1rem; color: #222; }}
  table {{ border-collapse: collapse; margin: 1rem 0; }}
  td, th {{ padding: 0.2rem 0.8rem; border-bottom: 1px solid #ddd; text-align: left; }}
  img {{ max-width: 100%; height: auto; border: 1px solid #eee; }}
  .skipped {{ color: #8a6d3b; background: #fcf8e3; padding: 0.5rem 0.8rem; border-radius: 4px; }}
  section {{ margin: 2rem 0; }}
</style>
</head>
<body>
<h1>{title}</h1>
<p>From <code>{source}</code>.</p>
{table}
{sections}
</body>
</html>
"""


def write_index(out, run_json, run, sections):
    rows = "".join(f"<tr><th>{html.escape(label)}</th><td>{html.escape(fmt.format(run[k]))}</td></tr>"
                   for k, label, fmt in METRICS if run.get(k) is not None)
    body = "\n".join(_section_html(out, s) for s in sections)
    page = PAGE.format(title=html.escape(f"edgepose report: {run_json.stem}"), source=html.escape(str(run_json)),
                       table=f"<table>{rows}</table>", sections=body)
    index = out / "index.html"
    index.write_text(page)
    return index


def _section_html(out, s):
    if s.image is None:
        return f'<section><h2>{html.escape(s.title)}</h2><p class="skipped">{html.escape(s.text)}</p></section>'
    from PIL import Image

    with Image.open(out / s.image) as im:
        w, h = im.size
    return (f'<section><h2>{html.escape(s.title)}</h2>'
            f'<img src="{html.escape(s.image)}" width="{w}" height="{h}" alt="{html.escape(s.title)}">'
            f'<p>{html.escape(s.text)}</p></section>')

