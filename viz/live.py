"""`edge listen PORT --plot`: a live 3D stick figure of the board's pose stream in a desktop window.

    from edgetools.listen import Listener, status_loop
    from viz.live import live_plot
    with Listener("/dev/ttyUSB0") as ear:
        live_plot(ear, seconds=30, fallback=status_loop)

Each POSE_FRAME carries the root position and the LOCAL joint rotations (edge.skeleton order); the
figure is their forward kinematics. Without a display (no DISPLAY or WAYLAND_DISPLAY, or matplotlib has
no GUI toolkit) it says so and runs `fallback` instead (the command passes the listener's status
line, edgetools.listen.status_loop, as plain `edge listen` shows). This module imports no tool: the
`edge` command (edgecli) puts the listener and the window together.
"""
import os
import sys
import time

import numpy as np

from edge import quat
from edge.skeleton import JOINT_NAMES, PARENTS, PELVIS_HEIGHT, REST, TOES, fk
from viz import canvas

DRAW_HZ = 30               # redraws per second; frames in between are read and counted, not drawn
STATUS_HZ = 4
NON_INTERACTIVE = {"agg", "cairo", "pdf", "pgf", "ps", "svg", "template"}


def has_display():
    """A desktop session to open a window in (X11 or Wayland)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def pose_positions(frame):
    """World joint positions [J,3] of a protocol.PoseFrame."""
    rotations = quat.to_matrix(np.asarray(frame.rotations, dtype=np.float64))
    return fk(rotations, np.asarray(frame.root_pos, dtype=np.float64))[1]


def live_plot(listener, seconds=None, fallback=None):
    """Draw the stream `listener` (anything with poll(timeout) -> pose frames and status_line(), as
    edgetools.listen.Listener) receives until the window is closed, Ctrl-C, or `seconds` pass. Without
    a display it runs fallback(listener, seconds) instead (returns 1 when there is none)."""
    plt = _interactive_pyplot()
    if plt is None:
        return fallback(listener, seconds) if fallback is not None else 1
    fig = plt.figure("edge listen", figsize=(6, 7))
    view = LiveView(fig)
    plt.show(block=False)
    start = last_draw = time.monotonic()
    latest = None
    try:
        while seconds is None or time.monotonic() - start < seconds:
            try:
                frames = listener.poll(0.01)
            except OSError as e:           # the port went away: say so, do not look like silence
                print(f"edge listen: {e}", file=sys.stderr)
                break
            latest = frames[-1] if frames else latest
            if not plt.fignum_exists(fig.number):
                break
            if latest is not None and time.monotonic() - last_draw >= 1.0 / DRAW_HZ:
                last_draw = time.monotonic()
                view.show(latest, listener.status_line())
                fig.canvas.draw_idle()
            fig.canvas.flush_events()
    except KeyboardInterrupt:
        pass
    plt.close(fig)
    print(listener.status_line(), file=sys.stderr)
    return 0


def _interactive_pyplot():
    """pyplot on a GUI backend, or None after saying why there is no window."""
    if not has_display():
        print("edge listen --plot: no display (DISPLAY and WAYLAND_DISPLAY are unset), so no window; "
              "showing the status line instead. Run it in a desktop session, or use ssh -X.", file=sys.stderr)
        return None
    canvas.require_plotting()
    import matplotlib.pyplot as plt

    if plt.get_backend().lower() in NON_INTERACTIVE:
        print(f"edge listen --plot: matplotlib has no GUI toolkit here (backend {plt.get_backend()}); showing the "
              "status line instead. Install one, e.g. apt-get install python3-tk.", file=sys.stderr)
        return None
    return plt


class LiveView:
    """A 3D stick figure on a figure, following the pelvis, Y up, feet marked while in contact."""

    REACH = 1.0            # metres shown either side of the pelvis

    def __init__(self, fig):
        from mpl_toolkits.mplot3d.art3d import Line3DCollection

        from viz.skeleton_draw import bone_order, lighter

        self.ax = fig.add_subplot(projection="3d")
        self.bones, sides = bone_order(PARENTS, JOINT_NAMES)
        colours = [lighter(canvas.PREDICTION) if s == "r_" else canvas.PREDICTION for s in sides]
        rest = REST + [0.0, PELVIS_HEIGHT, 0.0]
        self.lines = Line3DCollection([rest[[a, b]] for a, b in self.bones], colors=colours, linewidths=3)
        self.ax.add_collection3d(self.lines, autolim=False)
        self.feet = self.ax.plot([], [], [], "o", color="#333333", markersize=8)[0]
        self.ax.view_init(elev=12, azim=30, vertical_axis="y")   # three-quarter front view
        self.ax.set_box_aspect((1, 1, 1))
        self.ax.set_xlabel("x (m, left)")
        self.ax.set_ylabel("y (m, up)")
        self.ax.set_zlabel("z (m, front)")
        self.title = self.ax.set_title("waiting for pose frames ...", fontsize=8)

    def show(self, frame, status=""):
        """Draw one protocol.PoseFrame; `status` goes in the title."""
        p = pose_positions(frame)
        self.segments = [p[[a, b]] for a, b in self.bones]
        self.lines.set_segments(self.segments)
        down = TOES[np.asarray(frame.contacts) > 0.5]
        self.feet.set_data_3d(p[down, 0], p[down, 1], p[down, 2])
        cx, cz = p[0, 0], p[0, 2]
        self.ax.set_xlim(cx - self.REACH, cx + self.REACH)
        self.ax.set_ylim(0, 2 * self.REACH)
        self.ax.set_zlim(cz - self.REACH, cz + self.REACH)
        lost = [str(i) for i in range(16) if frame.trackers_lost >> i & 1]
        self.title.set_text(status.replace(" | ", "\n", 1) + (f"\ntrackers lost: {', '.join(lost)}" if lost else ""))
        return p
