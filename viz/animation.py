"""The moving picture: ground truth beside prediction as a looping GIF, front and side views.

The figure is built once and only the stick figures move from frame to frame, so a 5 s clip at
20 frames per second renders in a second or two.
"""
import numpy as np

from viz import canvas
from viz.skeleton_draw import StickFigure, body_views, shared_limits, style_panel


def skeleton_gif(gt, pred, parents, names, fps, frames, path, out_fps=20, title="", panel_height_in=2.4, dpi=90):
    """Animate `frames` (indices into gt/pred [T,J,3], in order) at `out_fps`; pick every
    round(fps / out_fps)-th frame of a clip for real-time playback. Panels, left to right: ground
    truth front and side, prediction front and side (ground truth in grey beneath). Side views look at
    the character's right side."""
    frames = np.asarray(frames)
    views = body_views(gt, pred, names, fps)
    limits = shared_limits(*(p[frames] for pair in views.values() for p in pair))
    half, bottom, top = limits
    panel_w = panel_height_in * 2 * half / (top - bottom)
    gap, head = 0.08, 0.75
    width, height = 4 * panel_w + 5 * gap + 0.15, panel_height_in + head + 0.1
    fig = canvas.new_figure(width, height, dpi=dpi)
    figures = []
    for k, (which, view) in enumerate([(0, "front"), (0, "side"), (1, "front"), (1, "side")]):
        x0 = gap + k * (panel_w + gap) + (0.15 if which else 0)
        ax = fig.add_axes([x0 / width, 0.1 / height, panel_w / width, panel_height_in / height])
        style_panel(ax, limits)
        who = "prediction" if which else "ground truth"
        ax.set_title(f"{who}: {view}", fontsize=8.5, color=canvas.PREDICTION if which else canvas.GROUND_TRUTH,
                     pad=3)
        ghost = StickFigure(ax, parents, names, canvas.GHOST, linewidth=1.6, joints=False, zorder=2) if which else None
        colour = canvas.PREDICTION if which else canvas.GROUND_TRUTH
        figures.append((views[view], which, ghost, StickFigure(ax, parents, names, colour)))
    caption = fig.text(gap / width, 1 - 0.16 / height, "", fontsize=9.5, weight="bold", va="center")
    fig.text(gap / width, 1 - 0.36 / height, "grey: ground truth beneath the prediction; lighter bones: the right side",
             fontsize=7.5, color=canvas.TEXT_MUTED, va="center")
    error_cm = np.linalg.norm(pred - gt, axis=-1).mean(-1) * 100
    images = []
    for f in frames:
        for (gt_points, pred_points), which, ghost, figure in figures:
            if ghost is not None:
                ghost.show(gt_points[f])
            figure.show((pred_points if which else gt_points)[f])
        caption.set_text(f"{title}   t = {f / fps:5.2f} s   error {error_cm[f]:4.1f} cm")
        images.append(canvas.pixels(fig))
    return canvas.save_gif(images, path, out_fps)
