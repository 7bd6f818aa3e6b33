"""Off-screen figures: matplotlib's Agg renderer without pyplot, and pixels out of it.

Report figures never go through pyplot, so they leave no global state behind (no open-figure list,
no backend switch) and `viz.live` can still open a desktop window in the same process.
"""
from pathlib import Path

import numpy as np

INSTALL_HINT = "pip install -e '.[viz]'  (matplotlib and pillow)"
DPI = 100

# Colours: ground truth blue, prediction orange; everything that is not a skeleton is grey, so the
# coloured pixels of a picture are exactly its skeletons.
GROUND_TRUTH = "#1e5ac8"
PREDICTION = "#d7602d"
GHOST = "#c4c4c4"          # ground truth drawn faintly under the prediction
FLOOR = "#9a9a9a"
GRID = "#e6e6e6"
TEXT_MUTED = "#555555"
BUDGET = "#c0392b"         # lines that mark a limit (frame budget, thresholds)


class MissingPlotting(SystemExit):
    """matplotlib or pillow is not installed."""


def require_plotting():
    """Import matplotlib and pillow, or stop with the command that installs them."""
    try:
        import matplotlib  # noqa: F401
        import PIL  # noqa: F401
    except ImportError as e:
        raise MissingPlotting(f"edgepose pictures need the [viz] extra ({e.name} is missing): {INSTALL_HINT}") from None


def new_figure(width_in, height_in, dpi=DPI):
    """A blank figure drawn by Agg, sized in inches."""
    require_plotting()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=dpi, facecolor="white")
    FigureCanvasAgg(fig)
    return fig


def pixels(fig):
    """Render a figure: [H,W,3] uint8 RGB."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def fit_width(rgb, width):
    """Crop or pad (white, on the right) an RGB image to exactly `width` pixels; figures sized in inches
    can come out a pixel short of the picture they are stacked on."""
    if rgb.shape[1] >= width:
        return rgb[:, :width]
    return np.pad(rgb, ((0, 0), (0, width - rgb.shape[1]), (0, 0)), constant_values=255)


def save_png(image_or_fig, path):
    """Write an RGB array or a figure as an optimised PNG; returns the path."""
    from PIL import Image

    rgb = pixels(image_or_fig) if hasattr(image_or_fig, "canvas") else image_or_fig
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).save(path, optimize=True)
    return path


def save_gif(frames, path, fps):
    """Write RGB frames [H,W,3] as a looping GIF playing at `fps`; returns the path."""
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    # One palette for the whole clip (taken from a frame with both skeletons), so colours do not flicker.
    palette = images[len(images) // 2].quantize(colors=32, method=Image.Quantize.MEDIANCUT)
    quantised = [im.quantize(palette=palette, dither=Image.Dither.NONE) for im in images]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    quantised[0].save(path, save_all=True, append_images=quantised[1:], duration=round(1000 / fps), loop=0,
                      optimize=False, disposal=1)
    return path
