"""The progress bar off a terminal (logs, CI): a line per tenth of the way, however the count moves."""
import io

from edge.progress import Progress


def test_off_a_terminal_jumping_counts_still_print_each_tenth_once():
    out = io.StringIO()
    bar = Progress(2700, "cvae (s)", stream=out)
    bar._last = -1.0
    for _ in range(90):              # the training loop sets n from the clock: steps of 30
        bar.n += 29
        bar._last = -1.0             # defeat the redraw throttle: every update draws
        bar.update()
    lines = out.getvalue().splitlines()
    assert len(lines) == 10
    assert lines[-1].startswith("cvae (s) [############################] 2700/2700")
