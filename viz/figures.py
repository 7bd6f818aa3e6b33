"""One function per picture. Each takes plain arrays, draws with Agg (viz.canvas) and writes a PNG.

    skeleton_strip     ground truth | prediction, every k-th frame, front and side views
    per_joint_errors   MPJPE of each joint as bars
    latency_histogram  frame latencies against the 60 Hz frame budget
    ssi_timeline       SSI: every sample's cost, the outlier bound, switches and the sample shown
    health_timeline    lost and recovered trackers, corrupt packets, injected faults
    contention_timeline  edge profile under a CPU hog: every frame's time and the N running
    soak_figure        edge soak: memory, descriptors, threads, the frame's tail and late ticks over hours

Data checks that decide whether a picture can be drawn at all live in viz.report.
"""
import numpy as np

from viz import canvas
from viz.skeleton_draw import VIEWS, StickFigure, body_views, shared_limits, style_panel

FRAME_BUDGET_MS = 1000.0 / 60.0


# --------------------------------------------------------------------------------------------------
# Skeleton strip


def skeleton_strip(gt, pred, parents, names, fps, frames, path, title="", panel_height_in=1.5,
                   colours=(canvas.GROUND_TRUTH, canvas.PREDICTION)):
    """Ground truth (left half) and prediction (right half) of the same `frames`, one column per frame,
    front view above side view. gt, pred [T,J,3] metres; `colours` for ground truth and prediction.
    The halves are drawn as two figures with the same layout and put side by side, so the same pose
    lands on the same pixels in both."""
    frames = np.asarray(frames)
    views = body_views(gt, pred, names, fps)
    limits = shared_limits(*(p[frames] for pair in views.values() for p in pair))
    error_cm = np.linalg.norm(pred[frames] - gt[frames], axis=-1).mean(-1) * 100
    halves = [_strip_half(views, 0, frames, fps, limits, parents, names, panel_height_in, colours[0], "Ground truth"),
              _strip_half(views, 1, frames, fps, limits, parents, names, panel_height_in, colours[1],
                          f"Prediction (mean error {error_cm.mean():.1f} cm)", error_cm)]
    body = np.concatenate(halves, axis=1)
    header = canvas.fit_width(_strip_header(body.shape[1] / canvas.DPI, title), body.shape[1])
    return canvas.save_png(np.concatenate([header, body], axis=0), path)


def _strip_header(width_in, title):
    fig = canvas.new_figure(width_in, 0.5)
    fig.text(0.01, 0.62, title, fontsize=11, weight="bold", va="center")
    fig.text(0.01, 0.2, "Left: ground truth (blue). Right: prediction (orange) with the ground truth in grey beneath "
             "it. Lighter bones: the right side. Views turn with the body; grid lines every 0.5 m above the floor.",
             fontsize=8.5, color=canvas.TEXT_MUTED, va="center")
    return canvas.pixels(fig)


def _strip_half(views, which, frames, fps, limits, parents, names, panel_h, colour, heading, error_cm=None):
    """One half of the strip: rows are views, columns are frames; `which` 0 = ground truth, 1 = prediction."""
    half, bottom, top = limits
    panel_w = panel_h * 2 * half / (top - bottom)
    left, top_margin, bottom_margin, gap = 0.3, 0.5, 0.22, 0.06
    width = left + len(frames) * (panel_w + gap)
    height = top_margin + len(VIEWS) * (panel_h + gap) + bottom_margin
    fig = canvas.new_figure(width, height)
    fig.text(left / width, 1 - 0.16 / height, heading, fontsize=10, weight="bold", va="center")
    for row, (view, label) in enumerate(VIEWS.items()):
        y0 = height - top_margin - (row + 1) * (panel_h + gap) + gap
        fig.text(0.12 / width, (y0 + panel_h / 2) / height, label.split(" ")[0], rotation=90, fontsize=8.5,
                 va="center", ha="center", color=canvas.TEXT_MUTED)
        for col, f in enumerate(frames):
            x0 = left + col * (panel_w + gap)
            ax = fig.add_axes([x0 / width, y0 / height, panel_w / width, panel_h / height])
            style_panel(ax, limits)
            if row == 0:
                ax.set_title(f"t = {f / fps:.2f} s", fontsize=8, color=canvas.TEXT_MUTED, pad=3)
            # Ground truth in grey beneath both skeletons: visible only where the prediction departs from it.
            StickFigure(ax, parents, names, canvas.GHOST, linewidth=1.6, joints=False, zorder=2).show(views[view][0][f])
            StickFigure(ax, parents, names, colour).show(views[view][which][f])
            if error_cm is not None and row == len(VIEWS) - 1:
                ax.text(0.5, -0.06, f"{error_cm[col]:.1f} cm", transform=ax.transAxes, ha="center", va="top",
                        fontsize=7.5, color=canvas.TEXT_MUTED)
    return canvas.pixels(fig)


# --------------------------------------------------------------------------------------------------
# Per-joint errors

BODY_PARTS = (("torso and head", "#6c757d", ("pelvis", "spine", "chest", "neck", "head")),
              ("left arm", "#2a9d8f", ("l_collar", "l_shoulder", "l_elbow", "l_wrist")),
              ("right arm", "#2a9d8f", ("r_collar", "r_shoulder", "r_elbow", "r_wrist")),
              ("left leg", "#7b4fa0", ("l_hip", "l_knee", "l_ankle", "l_toe")),
              ("right leg", "#7b4fa0", ("r_hip", "r_knee", "r_ankle", "r_toe")))


def per_joint_errors(errors_cm, names, path, title="Per-joint position error"):
    """Horizontal bars, joints top to bottom in skeleton order, coloured by body part (right side lighter),
    with the mean over joints (the MPJPE) as a dashed line."""
    from matplotlib.patches import Patch

    from viz.skeleton_draw import lighter

    errors_cm = np.asarray(errors_cm, dtype=float)
    colour_of = {n: (lighter(c) if part.startswith("right") else c) for part, c, joints in BODY_PARTS for n in joints}
    colours = [colour_of.get(n, "#6c757d") for n in names]
    height = 0.26 * len(names) + 1.3
    fig = canvas.new_figure(7.0, height)
    ax = fig.add_axes([0.15, 0.6 / height, 0.8, 1 - 1.1 / height])
    y = np.arange(len(names))
    ax.barh(y, errors_cm, color=colours, height=0.7)
    ax.set_yticks(y, names, fontsize=8.5)
    ax.invert_yaxis()
    ax.set_xlabel("mean position error (cm)")
    ax.set_title(title, fontsize=10.5, loc="left")
    reach = max(errors_cm.max(), 1e-6)
    for yi, e in zip(y, errors_cm, strict=True):
        ax.text(e + reach * 0.01, yi, f"{e:.1f}" if e >= 0.05 else "0 (tracked)", va="center", fontsize=7.5,
                color=canvas.TEXT_MUTED, bbox=dict(facecolor="white", edgecolor="none", pad=0.4), zorder=4)
    mean = errors_cm.mean()
    ax.axvline(mean, color="black", linestyle="--", linewidth=1)
    ax.set_xlim(0, reach * 1.15)
    ax.grid(axis="x", color=canvas.GRID)
    ax.set_axisbelow(True)
    handles = [Patch(color=BODY_PARTS[0][1], label="torso and head"),
               Patch(color=BODY_PARTS[1][1], label="arms"),
               Patch(color=BODY_PARTS[3][1], label="legs"),
               Patch(color=lighter("#888888"), label="lighter: right side"),
               _dashed_handle(f"mean over joints (MPJPE) {mean:.2f} cm")]
    ax.legend(handles=handles, loc="upper right", fontsize=7.5, framealpha=0.95)
    return canvas.save_png(fig, path)


def _dashed_handle(label, colour="black"):
    from matplotlib.lines import Line2D

    return Line2D([], [], color=colour, linestyle="--", linewidth=1, label=label)


# --------------------------------------------------------------------------------------------------
# Latency


def latency_histogram(samples_ms, path, budget_ms=FRAME_BUDGET_MS, title="Frame latency"):
    """Histogram of per-frame latencies with the frame budget, the median and the 99th percentile marked."""
    lat = np.asarray(samples_ms, dtype=float)
    p50, p99 = np.percentile(lat, [50, 99])
    over = (lat > budget_ms).mean() * 100
    fig = canvas.new_figure(7.0, 3.4)
    ax = fig.add_axes([0.1, 0.16, 0.86, 0.72])
    top = max(lat.max(), budget_ms) * 1.08
    ax.hist(lat, bins=np.linspace(0, top, 60), color="#5b7db1", edgecolor="white", linewidth=0.4)
    ax.axvline(budget_ms, color=canvas.BUDGET, linewidth=2, label=f"frame budget {budget_ms:.1f} ms (60 Hz)")
    ax.axvline(p50, color="black", linestyle="--", linewidth=1, label=f"median {p50:.1f} ms")
    ax.axvline(p99, color="black", linestyle=":", linewidth=1.2, label=f"99th percentile {p99:.1f} ms")
    ax.set_xlim(0, top)
    ax.set_xlabel("latency (ms)")
    ax.set_ylabel("frames")
    ax.set_title(f"{title}: {len(lat)} frames, {over:.1f}% over budget", fontsize=10.5, loc="left")
    ax.legend(fontsize=8)
    return canvas.save_png(fig, path)


# --------------------------------------------------------------------------------------------------
# SSI


def outlier_bound(cost):
    """The cost above which the current sample counts as an outlier (edge.ssi.is_outlier):
    min + 2 (median - min) over the samples, per frame. cost [T,N] -> [T]."""
    lo = cost.min(axis=1)
    return lo + 2.0 * (np.median(cost, axis=1) - lo)


def ssi_timeline(cost, sample, transition, switches, threshold, fps, warmup_frames, path, title="SSI sample selection"):
    """Two stacked panels over time.

    Top: every sample's selection cost (lower-body autoencoder error, shown in cm; thin lines), the cost
    of the sample shown (thick), the outlier bound that triggers a switch, the plausibility threshold, and
    the frames where a switch was detected. Bottom: which sample is shown, transitions shaded.
    cost [T,N] metres, sample [T], transition [T] bool, switches [K,2] (detected frame, first transition
    frame), threshold metres.
    """
    T, N = cost.shape
    t = np.arange(T) / fps
    cost_cm, threshold_cm = cost * 100, threshold * 100
    fig = canvas.new_figure(10.0, 5.4)
    top = fig.add_axes([0.08, 0.4, 0.68, 0.52])
    bottom = fig.add_axes([0.08, 0.1, 0.68, 0.2], sharex=top)
    palette = _sample_colours(N)
    for n in range(N):
        top.plot(t, cost_cm[:, n], color=palette[n], linewidth=0.8, alpha=0.75)
    top.plot(t, cost_cm[np.arange(T), sample], color="black", linewidth=2.0, label="sample shown")
    top.plot(t, outlier_bound(cost_cm), color=canvas.BUDGET, linestyle=":", linewidth=1.3,
             label="outlier bound:\nmin + 2 (median - min)")
    top.axhline(threshold_cm, color=canvas.BUDGET, linestyle="--", linewidth=1.2,
                label=f"plausibility threshold {threshold_cm:.1f} cm")
    _log_scale_in_plain_numbers(top, cost_cm, threshold_cm)
    top.set_ylabel("selection cost (cm)")
    top.set_title(title, fontsize=10.5, loc="left")
    for ax in (top, bottom):
        ax.axvspan(0, warmup_frames / fps, color="#eeeeee", zorder=0, label="warm-up (not scored)")
        _shade_spans(ax, t, transition, "#f3d9a4", "transition")
        for detected, _ in np.asarray(switches).reshape(-1, 2):
            ax.axvline(detected / fps, color="#333333", linewidth=0.9, alpha=0.8)
    top.plot([], [], color="#333333", linewidth=0.9, label=f"switch detected ({len(switches)})")
    for n in range(N):
        top.plot([], [], color=palette[n], linewidth=2, label=f"sample {n}")
    top.legend(fontsize=7.5, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    top.tick_params(labelbottom=False)
    bottom.step(t, sample, where="post", color="black", linewidth=1.0)
    every = max(1, T // 400)
    bottom.scatter(t[::every], sample[::every], c=[palette[s] for s in sample[::every]], s=5, zorder=3)
    bottom.set_yticks(range(N))
    bottom.set_ylim(-0.5, N - 0.5)
    bottom.set_ylabel("sample shown", fontsize=8.5)
    bottom.tick_params(axis="y", labelsize=7)
    bottom.set_xlabel("time (s)")
    bottom.set_xlim(0, t[-1])
    return canvas.save_png(fig, path)


def _log_scale_in_plain_numbers(ax, values, *also):
    """A log axis (costs span a decade) labelled 1, 2, 5, 10, ... instead of powers of ten."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    if not np.all(values > 0):
        return
    ax.set_yscale("log")
    lo, hi = values.min(), max(values.max(), *also)
    ax.set_ylim(lo / 1.15, hi * 1.15)
    ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def _sample_colours(n):
    from matplotlib import colormaps

    cmap = colormaps["tab10" if n <= 10 else "viridis"]
    return [cmap(i if n <= 10 else i / max(n - 1, 1)) for i in range(n)]


def _shade_spans(ax, t, mask, colour, label):
    """Shade the runs where mask is true (label only the first, for the legend)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    dt = t[1] - t[0] if len(t) > 1 else 1.0
    for k, (a, b) in enumerate(zip(edges[::2], edges[1::2], strict=True)):
        ax.axvspan(t[a], t[b - 1] + dt, color=colour, zorder=0, label=label if k == 0 else None)


# --------------------------------------------------------------------------------------------------
# Tracker health


def check_health_timeline(health):
    """Raise ValueError saying what is wrong if `health` is not the format health_timeline draws:

        {"t":       [seconds, ...],                    one entry per frame, increasing
         "lost":    {"waist": [0, 0, 1, ...], ...},    per tracker (or headset / controller), 1 while lost
         "corrupt": [0, 0, 2, ...],                    optional: corrupt packets received in that frame
         "faults":  [{"t": 3.2, "kind": "unplug waist"}, ...]}   optional: faults the simulator injected

    A tracker is "recovered" where its lost flag falls from 1 to 0.
    """
    if not isinstance(health, dict) or "t" not in health:
        raise ValueError("health_timeline must be an object with a 't' list of frame times")
    T = len(health["t"])
    if T < 2:
        raise ValueError("health_timeline['t'] needs at least two frames")
    lost = health.get("lost", {})
    if not isinstance(lost, dict):
        raise ValueError("health_timeline['lost'] must map tracker names to 0/1 lists")
    for name, flags in lost.items():
        if len(flags) != T:
            raise ValueError(f"health_timeline['lost'][{name!r}] has {len(flags)} entries, 't' has {T}")
    if "corrupt" in health and len(health["corrupt"]) != T:
        raise ValueError(f"health_timeline['corrupt'] has {len(health['corrupt'])} entries, 't' has {T}")
    for fault in health.get("faults", []):
        if not (isinstance(fault, dict) and "t" in fault and "kind" in fault):
            raise ValueError(f"each health_timeline fault needs 't' and 'kind', got {fault!r}")


def health_timeline(health, path, title="Tracker health"):
    """Rows over time: injected faults (labelled, with a dashed line through every row), one row per tracker
    with its lost spans (red) and recoveries (green triangles), and corrupt packets per frame (ticks)."""
    check_health_timeline(health)
    t = np.asarray(health["t"], dtype=float)
    lost = {k: np.asarray(v, dtype=bool) for k, v in health.get("lost", {}).items()}
    corrupt = np.asarray(health.get("corrupt", np.zeros(len(t))), dtype=float)
    faults = health.get("faults", [])
    rows = ["injected faults", *lost, "corrupt packets"]
    height = 0.5 * len(rows) + 1.0
    fig = canvas.new_figure(10.0, height)
    ax = fig.add_axes([0.13, 0.55 / height, 0.65, 1 - 0.9 / height])
    dt = float(np.median(np.diff(t)))
    for k, fault in enumerate(faults):
        ax.axvline(fault["t"], color="#7b4fa0", linestyle="--", linewidth=1, zorder=1)
        ax.plot(fault["t"], 0, "D", color="#7b4fa0", markersize=6, label="injected fault" if k == 0 else None)
        ax.text(fault["t"], -0.32, f" {fault['kind']}", fontsize=7.5, color="#7b4fa0", va="center",
                bbox=dict(facecolor="white", edgecolor="none", pad=0.3))
    for row, flags in enumerate(lost.values(), start=1):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], flags.astype(int), [0]])))
        spans = [(t[a], t[b - 1] + dt - t[a]) for a, b in zip(edges[::2], edges[1::2], strict=True)]
        ax.broken_barh(spans, (row - 0.3, 0.6), color="#d9534f", zorder=2, label="lost" if row == 1 else None)
        back = [t[b] for b in edges[1::2] if b < len(t)]
        ax.plot(back, [row] * len(back), "^", color="#2e8b57", markersize=8, zorder=3,
                label="recovered" if row == 1 else None)
    row, peak = len(rows) - 1, max(corrupt.max(), 1.0)
    hit = corrupt > 0
    if hit.any():                   # no legend entry for what did not happen
        ax.vlines(t[hit], row + 0.3, row + 0.3 - 0.6 * corrupt[hit] / peak, color="#444444", linewidth=1.2,
                  label=f"corrupt packets (tallest tick: {peak:.0f})")
    ax.set_yticks(range(len(rows)), rows, fontsize=8.5)
    ax.set_ylim(len(rows) - 0.5, -0.5)
    ax.set_xlim(t[0], t[-1] + dt)
    ax.set_xlabel("time (s)")
    ax.set_title(title, fontsize=10.5, loc="left")
    ax.grid(axis="x", color=canvas.GRID)
    ax.set_axisbelow(True)
    if ax.get_legend_handles_labels()[1]:       # a clean run has nothing to explain
        ax.legend(fontsize=7.5, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    return canvas.save_png(fig, path)


# --------------------------------------------------------------------------------------------------
# Adaptive N under contention


def contention_timeline(frame_ms, samples_timeline, period_ms, hog, path, title="Adaptive N under a CPU hog"):
    """Two panels over time: each frame's response time against the deadline (misses in red), and the
    number of samples running. `samples_timeline` is [[first frame, N], ...]; `hog` {"start_frame",
    "frames", "processes"} or None. Frames at 1000/period_ms Hz."""
    from matplotlib.ticker import NullFormatter

    ms = np.asarray(frame_ms, dtype=float)
    t = np.arange(len(ms)) * period_ms / 1000.0
    n = np.empty(len(ms))
    for (a, v), nxt in zip(samples_timeline, samples_timeline[1:] + [[len(ms), None]], strict=True):
        n[a:nxt[0]] = v
    fig = canvas.new_figure(8.0, 4.6)
    top = fig.add_axes([0.09, 0.52, 0.88, 0.38])
    bottom = fig.add_axes([0.09, 0.11, 0.88, 0.33], sharex=top)
    late = ms > period_ms
    for ax in (top, bottom):
        if hog:
            a, b = hog["start_frame"], hog["start_frame"] + hog["frames"]
            ax.axvspan(a * period_ms / 1000.0, b * period_ms / 1000.0, color="#f3e2c7", zorder=0,
                       label=f"{hog['processes']} busy processes on the core" if ax is top else None)
        ax.grid(color=canvas.GRID, linewidth=0.6)
    top.plot(t[~late], ms[~late], ".", markersize=1.6, color="#5b7db1", label="frame (release to done)")
    top.plot(t[late], ms[late], ".", markersize=3.5, color=canvas.BUDGET, label=f"late: {int(late.sum())} frames")
    top.axhline(period_ms, color=canvas.BUDGET, linewidth=1.2, label=f"deadline {period_ms:.1f} ms")
    top.set_ylim(0, max(2.2 * period_ms, np.percentile(ms, 99.5) * 1.1))
    top.set_ylabel("ms")
    top.legend(fontsize=7.5, loc="upper right", markerscale=3)
    top.set_title(f"{title}: {len(ms)} frames, {100 * late.mean():.2f} % late", fontsize=10.5, loc="left")
    bottom.step(t, n, where="post", color="#2d7d46", linewidth=1.5)
    bottom.set_yscale("log", base=2)
    ticks = [v for v in (1, 2, 4, 8, 16, 32, 64, 128) if v <= n.max() * 1.01]
    bottom.set_yticks(ticks, [str(v) for v in ticks])
    bottom.yaxis.set_minor_formatter(NullFormatter())
    bottom.set_ylim(0.8, max(n.max() * 1.4, 2))
    bottom.set_ylabel("samples N")
    bottom.set_xlabel("time (s)")
    return canvas.save_png(fig, path)


# --------------------------------------------------------------------------------------------------
# Training


def read_train_log(path, people="unseen"):
    """models.train's log -> (steps, val none cm, val imus cm) arrays, steps counted from the first run
    when a log holds a resumed run ('resumed from ... after K steps' shifts what follows by K). Logs
    that validate on unseen and seen people apart give `people`'s; older logs their one val."""
    import re
    steps, none, imus, base = [], [], [], 0
    for line in open(path):
        if m := re.search(r"resumed from .* after (\d+) steps", line):
            base = int(m.group(1))
        elif m := re.match(r"it (\d+) .*val mpjpe [^|]*?(?:" + people + r" )?none ([\d.]+) (?:" + people
                           + r" )?imus ([\d.]+)", line):
            steps.append(base + int(m.group(1)))
            none.append(float(m.group(2)))
            imus.append(float(m.group(3)))
    return np.array(steps), np.array(none), np.array(imus)


def learning_curves(runs, path, title="Validation error against training steps"):
    """runs: {label: train_log path}. Val MPJPE (head-anchored, no IK, prior mean) against Adam steps,
    no IMUs solid and random IMU sets dashed, one colour a run."""
    fig = canvas.new_figure(7.0, 3.6)
    ax = fig.add_axes([0.1, 0.15, 0.86, 0.74])
    for (label, log), colour in zip(runs.items(), _sample_colours(len(runs)), strict=True):
        steps, none, imus = read_train_log(log)
        ax.plot(steps, none, "-o", color=colour, markersize=3, label=f"{label}: no extra IMUs")
        ax.plot(steps, imus, "--o", color=colour, markersize=3, label=f"{label}: random IMU sets")
    ax.set_xlabel("Adam steps")
    ax.set_ylabel("val MPJPE, cm (no IK)")
    ax.set_title(title, fontsize=10.5, loc="left")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return canvas.save_png(fig, path)


# --------------------------------------------------------------------------------------------------
# Soak


def soak_figure(rows, summary, path, title="edge soak"):
    """Four panels over the soak's minutes, from its samples (edgetools.sim.soak's JSON lines): RSS;
    descriptors and threads; the frame's p50 and p99 in each sample; late ticks by whose doing, summed.
    The injected faults are marks along the bottom."""
    t = np.array([r["t_min"] for r in rows], float)
    fig = canvas.new_figure(8.0, 7.2)
    axes = [fig.add_axes([0.1, 0.77 - 0.225 * i, 0.86, 0.17]) for i in range(4)]
    rss, fds, threads = ([r[k] for r in rows] for k in ("rss_mb", "fds", "threads"))
    axes[0].plot(t, rss, "-o", markersize=2.5, color="#5b7db1")
    axes[0].set_ylabel("RSS (MB)")
    axes[0].set_title(f"{title}: {summary['minutes']:g} min, RSS {summary['rss_growth_mb_per_h']:+.2f} MB/h after "
                      f"warm-up, {summary['faults_recovered']}/{summary['faults_injected']} faults recovered, "
                      + ("ok" if summary["ok"] else "FAILED"), fontsize=9.5, loc="left")
    axes[1].step(t, fds, where="post", color="#2d7d46", label="open descriptors")
    axes[1].step(t, threads, where="post", color="#a05a2c", label="threads")
    axes[1].set_ylim(0, max(max(fds), max(threads)) * 1.3)
    axes[1].legend(fontsize=7.5, loc="lower right")
    for key, colour in (("frame_ms_p50", "#5b7db1"), ("frame_ms_p99", canvas.BUDGET)):
        axes[2].plot(t, [r[key] if r[key] is not None else np.nan for r in rows], "-", color=colour,
                     label=key.replace("frame_ms_", "frame ").replace("p", "p", 1))
    axes[2].set_ylabel("ms")
    axes[2].legend(fontsize=7.5, loc="upper right")
    colours = {"own": canvas.BUDGET, "fault": "#d9a13b", "host": "#7a7a7a", "harness": "#5b7db1"}
    for kind, colour in colours.items():
        axes[3].step(t, np.cumsum([r["late"][kind] for r in rows]), where="post", color=colour,
                     label=f"late, {kind}: {summary['late_frames'][kind]}")
    axes[3].set_ylabel("late ticks (sum)")
    axes[3].legend(fontsize=7, loc="upper left", ncol=2)
    axes[3].set_xlabel("minutes")
    marks = [e["at_s"] / 60 for e in summary.get("faults", [])]
    for ax in axes:
        ax.grid(color=canvas.GRID, linewidth=0.6)
        ax.set_xlim(0, max(t.max() if len(t) else 1, summary["minutes"]))
    axes[3].plot(marks, np.zeros(len(marks)), "|", color="black", markersize=8, label="faults")
    return canvas.save_png(fig, path)
