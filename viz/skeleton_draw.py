"""Stick figures in 2D: body-facing front and side views of world joint positions, and drawing them.

World positions are metres, Y-up (edge.skeleton). To see a pose rather than where someone walked,
each frame is moved so the ground-truth pelvis stands over the origin and turned so the ground-truth
body faces +Z. The prediction gets the same move as the ground truth of its frame, so an offset or a
turned torso in the prediction stays visible.

    front: seen from in front, the character's left on the right of the picture
    side:  seen from the character's right, facing right

Bones of the left side are drawn in the full colour, the right side lighter, the spine and head full.
"""
import numpy as np

from viz import canvas

VIEWS = {"front": "front", "side": "side (from the right)"}
GRID_M = 0.5               # horizontal grid lines every half metre: the scale of every panel


# --------------------------------------------------------------------------------------------------
# Geometry


def facing_angles(positions, names, fps, smooth_s=0.5):
    """Heading (yaw about +Y, radians; 0 = facing +Z) of each frame [T] from the hips and shoulders,
    smoothed over `smooth_s` seconds so the gait's hip swing does not rock the camera."""
    j = {n: i for i, n in enumerate(names)}
    left = (positions[:, j["l_hip"]] - positions[:, j["r_hip"]]
            + positions[:, j["l_shoulder"]] - positions[:, j["r_shoulder"]])
    forward_x, forward_z = -left[:, 2], left[:, 0]          # forward = left x up
    yaw = np.unwrap(np.arctan2(forward_x, forward_z))
    width = max(1, int(round(smooth_s * fps)) | 1)           # odd window, centred
    padded = np.pad(yaw, width // 2, mode="edge")
    return np.convolve(padded, np.ones(width) / width, mode="valid")


def to_body_frame(positions, centre, yaw):
    """Move [T,J,3] positions so `centre` [T,3] is over the origin (height kept) and rotate by -yaw [T]
    about +Y: +X is then the body's left and +Z its front."""
    p = positions - np.stack([centre[:, 0], np.zeros(len(centre)), centre[:, 2]], axis=-1)[:, None]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    return np.stack([p[..., 0] * c - p[..., 2] * s, p[..., 1], p[..., 0] * s + p[..., 2] * c], axis=-1)


def project(body_positions, view):
    """[...,J,3] body-frame positions -> [...,J,2] picture coordinates (horizontal, up) for a view."""
    horizontal = {"front": 0, "side": 2}[view]
    return body_positions[..., [horizontal, 1]]


def body_views(gt, pred, names, fps):
    """Ground truth and prediction [T,J,3] -> {view: (gt [T,J,2], pred [T,J,2])}, both moved and turned
    by the ground truth's pelvis and heading."""
    yaw = facing_angles(gt, names, fps)
    centre = gt[:, 0]
    gt_b, pred_b = to_body_frame(gt, centre, yaw), to_body_frame(pred, centre, yaw)
    return {v: (project(gt_b, v), project(pred_b, v)) for v in VIEWS}


def shared_limits(*points, margin=0.12):
    """One set of axis limits for every panel, so all skeletons share a scale:
    (horizontal half-width, bottom, top) in metres, the floor always in view."""
    allp = np.concatenate([p.reshape(-1, 2) for p in points])
    half = float(np.abs(allp[:, 0]).max()) + margin
    bottom = min(0.0, float(allp[:, 1].min())) - margin / 2
    top = float(allp[:, 1].max()) + margin
    return half, bottom, top


# --------------------------------------------------------------------------------------------------
# Drawing


def lighter(colour, amount=0.45):
    """A colour mixed with white (keeps the hue; scales the saturation by 1 - amount)."""
    from matplotlib.colors import to_rgb

    return tuple(c + (1 - c) * amount for c in to_rgb(colour))


def bone_order(parents, names):
    """Bones as (parent, child) pairs, left side first and right side last, with each bone's side."""
    bones = [(int(parents[j]), j) for j in range(len(parents)) if parents[j] >= 0]
    side = lambda child: names[child][:2] if names[child][:2] in ("l_", "r_") else "c"  # noqa: E731
    rank = {"l_": 0, "c": 1, "r_": 2}
    bones.sort(key=lambda b: rank[side(b[1])])
    return bones, [side(c) for _, c in bones]


class StickFigure:
    """One skeleton on a 2D axes: bones as a line collection, joints as dots. `show(points)` moves it."""

    def __init__(self, ax, parents, names, colour, linewidth=2.2, joints=True, zorder=3):
        from matplotlib.collections import LineCollection

        self.bones, sides = bone_order(parents, names)
        colours = [lighter(colour) if s == "r_" else colour for s in sides]
        self.lines = LineCollection([], colors=colours, linewidths=linewidth, capstyle="round", zorder=zorder)
        ax.add_collection(self.lines)
        self.dots = None
        if joints:
            self.dots = ax.plot([], [], "o", color=colour, markersize=linewidth * 1.1, zorder=zorder + 0.1)[0]

    def show(self, points):
        """points [J,2] picture coordinates."""
        self.lines.set_segments([points[[a, b]] for a, b in self.bones])
        if self.dots is not None:
            self.dots.set_data(points[:, 0], points[:, 1])


def style_panel(ax, limits):
    """Equal scales, the shared limits, the floor, half-metre grid lines, no ticks."""
    half, bottom, top = limits
    ax.set_xlim(-half, half)
    ax.set_ylim(bottom, top)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xticks([])
    ax.set_yticks([])
    for level in np.arange(GRID_M, top, GRID_M):
        ax.axhline(level, color=canvas.GRID, linewidth=0.8, zorder=0)
    ax.axhline(0.0, color=canvas.FLOOR, linewidth=1.4, zorder=1)
    for spine in ax.spines.values():
        spine.set_color(canvas.GRID)
