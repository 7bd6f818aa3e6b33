"""Reports and pictures (viz/): every figure from a short real run, read back as pixels.

One `edge eval --samples 8 --max-frames 300 --dump` run on the bundled sample feeds every test here.
A picture passes when it decodes, is not blank, and shows what its data says: the prediction half of the
skeleton strip departs from the ground-truth half exactly where the poses differ.
"""
import html
import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("matplotlib", reason="needs matplotlib for pictures: pip install -e '.[viz]'")
pytest.importorskip("PIL", reason="needs pillow for pictures: pip install -e '.[viz]'")
from PIL import Image  # noqa: E402

from edgecli import main as edge_main  # noqa: E402
from edge.skeleton import JOINT, PELVIS_HEIGHT, REST  # noqa: E402
from firmware_bridge.wire import messages  # noqa: E402
from edgetools.listen import Listener  # noqa: E402
from tests.conftest import ROOT, SAMPLE  # noqa: E402
from viz import canvas  # noqa: E402
from viz.figures import skeleton_strip  # noqa: E402
from viz.skeleton_draw import body_views  # noqa: E402
from viz.live import LiveView, pose_positions  # noqa: E402
from edgecli import listen_plot_loop  # noqa: E402
from viz.report import build_report, choose_clip  # noqa: E402

FIGURES = ("skeleton_strip.png", "animation.gif", "ssi_timeline.png", "per_joint_error.png")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A real evaluation: 300 frames of the sample walk, 8 SSI samples, metrics JSON and dump."""
    d = tmp_path_factory.mktemp("run")
    assert edge_main(["eval", "--data", str(SAMPLE), "--samples", "8", "--max-frames", "300",
                      "--json", str(d / "eval.json"), "--dump", str(d / "dump")]) == 0
    return d / "eval.json", d / "dump"


@pytest.fixture(scope="module")
def report(run, tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    build_report(run[0], out, dump=run[1], gif_seconds=1.0)
    return out


@pytest.fixture(scope="module")
def clip(run):
    d = np.load(run[1] / (SAMPLE.stem + ".npz"))
    return {k: d[k] for k in d.files}


def assert_picture(path):
    """Decodes, and is not one flat colour."""
    with Image.open(path) as im:
        rgb = np.asarray(im.convert("RGB"), dtype=float)
    assert rgb.shape[0] > 100 and rgb.shape[1] > 100, path
    assert rgb.std() > 10, f"{path.name} is (nearly) blank"


def skeleton_ink(path):
    """The strip's two halves with everything but coloured (skeleton) pixels whited out."""
    rgb = np.asarray(Image.open(path).convert("RGB")).astype(int)
    coloured = rgb.max(-1) - rgb.min(-1) > 30
    ink = np.where(coloured[..., None], rgb, 255)
    half = rgb.shape[1] // 2
    return ink[:, :half], ink[:, half:]


def strip(clip, pred, path, frames):
    names = [str(n) for n in clip["joint_names"]]
    one_colour = (canvas.PREDICTION, canvas.PREDICTION)     # so equal poses give equal pixels
    return skeleton_strip(clip["gt_pos"], pred, clip["parents"], names, float(clip["fps"]), frames, path,
                          colours=one_colour)


# --------------------------------------------------------------------------------------------------
# The report from a real run


def test_report_draws_every_figure_the_eval_run_allows(report):
    for name in FIGURES:
        assert_picture(report / name)
    with Image.open(report / "animation.gif") as gif:
        assert gif.n_frames > 1
        frames = []
        for k in (0, gif.n_frames - 1):
            gif.seek(k)
            frames.append(np.asarray(gif.convert("RGB"), dtype=int))
    assert np.abs(frames[0] - frames[1]).sum() > 0, "the animation does not move"


def test_index_html_shows_every_picture_and_says_what_it_skipped(report):
    page = (report / "index.html").read_text()
    shown = set(re.findall(r'<img src="([^"]+)"', page))
    assert shown == set(FIGURES)
    # An eval JSON has no latency samples and no health timeline; the page says so instead of drawing.
    assert re.search(r"Skipped: RUN.json has no latency_ms_samples", page)
    assert re.search(r"Skipped: RUN.json has no health_timeline", page)
    assert "MPJPE" in page


def test_strip_halves_are_identical_when_the_prediction_is_the_ground_truth(clip, tmp_path):
    frames = np.arange(60, 300, 20)[:6]
    left, right = skeleton_ink(strip(clip, clip["gt_pos"], tmp_path / "same.png", frames))
    assert (left < 255).any()
    assert np.array_equal(left, right)


def test_strip_prediction_half_differs_from_ground_truth_where_the_poses_differ(clip, tmp_path):
    frames = np.arange(60, 300, 20)[:6]
    left, right = skeleton_ink(strip(clip, clip["pred_pos"], tmp_path / "real.png", frames))
    assert (left != right).any(-1).mean() > 0.01

    # Lower the left forearm in one frame only: the halves differ in that frame's column and nowhere else,
    # and a later frame moves the difference to the right.
    def columns_changed(k):
        pred = clip["gt_pos"].copy()
        pred[frames[k], [JOINT["l_elbow"], JOINT["l_wrist"]], 1] -= 0.15
        a, b = skeleton_ink(strip(clip, pred, tmp_path / f"frame{k}.png", frames))
        return np.flatnonzero((a != b).any(-1).any(0))

    early, late = columns_changed(1), columns_changed(4)
    column_width = left.shape[1] / len(frames)
    assert len(early) and early.max() - early.min() < column_width
    assert len(late) and late.max() - late.min() < column_width
    assert late.min() > early.max()


def test_views_turn_with_the_body_and_show_its_left_on_the_right_from_the_front(clip):
    names, fps = [str(n) for n in clip["joint_names"]], float(clip["fps"])
    gt, pred = clip["gt_pos"][:120].astype(float), clip["pred_pos"][:120].astype(float)
    views = body_views(gt, pred, names, fps)
    # The same motion walked 3 m away and turned a quarter turn looks the same from the front and the side.
    c, s = np.cos(np.pi / 2), np.sin(np.pi / 2)
    turn = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    moved = body_views(gt @ turn.T + [3.0, 0, -2.0], pred @ turn.T + [3.0, 0, -2.0], names, fps)
    for v in views:
        for a, b in zip(views[v], moved[v], strict=True):
            assert np.allclose(a, b, atol=1e-6)
    front = views["front"][0]
    assert (front[:, JOINT["l_shoulder"], 0] > front[:, JOINT["r_shoulder"], 0]).all()
    side = views["side"][0]
    assert (side[:, JOINT["l_toe"], 0] > side[:, JOINT["l_ankle"], 0]).mean() > 0.9   # toes point right


def test_single_sample_dump_gets_no_ssi_timeline_and_the_page_says_why(run, clip, tmp_path):
    dump = tmp_path / "dump"
    dump.mkdir()
    np.savez(dump / (SAMPLE.stem + ".npz"), **{**clip, "cost": np.zeros((len(clip["cost"]), 1), np.float32),
                                               "sample": np.zeros_like(clip["sample"])})
    build_report(run[0], tmp_path / "out", dump=dump, gif_seconds=0.5)
    assert not (tmp_path / "out" / "ssi_timeline.png").exists()
    assert "one latent sample (N = 1)" in (tmp_path / "out" / "index.html").read_text()


# --------------------------------------------------------------------------------------------------
# Data the simulator will add: latency samples and a tracker-health timeline


def synthetic_health(frames=600, fps=60.0):
    t = np.arange(frames) / fps
    waist = ((t > 2.0) & (t < 3.3)) | ((t > 6.7) & (t < 7.2))
    controller = (t > 5.0) & (t < 5.5)
    corrupt = np.zeros(frames, int)
    corrupt[[50, 51, 250, 260, 261]] = [1, 2, 1, 3, 1]
    return {"t": t.round(4).tolist(), "lost": {"waist": waist.astype(int).tolist(),
                                               "left controller": controller.astype(int).tolist()},
            "corrupt": corrupt.tolist(),
            "faults": [{"t": 1.75, "kind": "unplug waist"}, {"t": 4.1, "kind": "bit flips"}]}


def test_latency_and_health_are_drawn_when_the_json_carries_them(run, tmp_path):
    result = json.loads(run[0].read_text())
    result["latency_ms_samples"] = (np.random.default_rng(0).gamma(6, 1.6, 2000) + 2).tolist()
    result["health_timeline"] = synthetic_health()
    sim = tmp_path / "sim.json"
    sim.write_text(json.dumps(result))
    build_report(sim, tmp_path / "out")
    for name in ("latency.png", "health_timeline.png", "per_joint_error.png"):
        assert_picture(tmp_path / "out" / name)
    page = (tmp_path / "out" / "index.html").read_text()
    assert '<img src="latency.png"' in page and '<img src="health_timeline.png"' in page
    assert "no --dump folder given" in page


def test_a_profile_run_under_a_hog_gets_its_contention_picture(tmp_path):
    out = tmp_path / "hog.json"
    assert edge_main(["profile", "--samples", "8", "--adaptive", "--frames", "90", "--hog-at", "0.5",
                      "--hog-seconds", "0.5", "--hog-procs", "1", "--no-cgroup", "--json", str(out)]) == 0
    build_report(out, tmp_path / "rep")
    assert_picture(tmp_path / "rep" / "contention.png")
    page = (tmp_path / "rep" / "index.html").read_text()
    assert '<img src="contention.png"' in page and "during: " in page


def test_malformed_health_timeline_is_skipped_with_the_reason(run, tmp_path):
    result = json.loads(run[0].read_text())
    health = synthetic_health()
    health["lost"]["waist"] = health["lost"]["waist"][:-5]
    result["health_timeline"] = health
    (tmp_path / "bad.json").write_text(json.dumps(result))
    build_report(tmp_path / "bad.json", tmp_path / "out")
    assert not (tmp_path / "out" / "health_timeline.png").exists()
    page = html.unescape((tmp_path / "out" / "index.html").read_text())
    assert "Skipped: health_timeline['lost']['waist'] has 595 entries, 't' has 600" in page


def test_default_clip_is_the_worst_and_an_unknown_clip_lists_the_choices(tmp_path):
    for stem in ("walk", "jump"):
        (tmp_path / f"{stem}.npz").touch()
    run = {"per_clip": [{"clip": "data/walk.bvh", "mpjpe_cm": 4.0}, {"clip": "data/jump.bvh", "mpjpe_cm": 9.0}]}
    assert choose_clip(tmp_path, run).stem == "jump"
    assert choose_clip(tmp_path, run, "walk.bvh").stem == "walk"
    with pytest.raises(ValueError, match="no clip 'run'.*jump, walk"):
        choose_clip(tmp_path, run, "run")


def test_missing_plotting_library_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(canvas.MissingPlotting, match=r"\[viz\]"):
        canvas.require_plotting()


def test_board_runtime_never_imports_plotting():
    code = ("import sys, edgecli, edgetools.eval, edge.pipeline, edgetools.listen, firmware_bridge.service, "
            "viz, viz.report, viz.live, viz.figures\n"
            "loaded = sorted(m for m in sys.modules if m.split('.')[0] in ('matplotlib', 'PIL'))\n"
            "assert not loaded, loaded")
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True)


# --------------------------------------------------------------------------------------------------
# edge listen --plot


def test_live_view_draws_the_forward_kinematics_of_a_pose_frame():
    rest = messages.PoseFrame(t=0.0, root_pos=np.array([0.3, PELVIS_HEIGHT, -1.0]),
                              rotations=np.tile([1.0, 0, 0, 0], (21, 1)), contacts=np.array([1.0, 0.0]))
    p = pose_positions(rest)
    assert np.allclose(p, REST + rest.root_pos)
    view = LiveView(canvas.new_figure(5, 6))
    view.show(rest, "status")
    segments = {(a, b): s for (a, b), s in zip(view.bones, view.segments, strict=True)}
    assert np.allclose(segments[(JOINT["l_knee"], JOINT["l_ankle"])], p[[JOINT["l_knee"], JOINT["l_ankle"]]])
    assert np.allclose(np.array(view.feet.get_data_3d()).T, p[[JOINT["l_toe"]]])   # only the left foot is down


def test_listen_plot_without_a_display_says_so_and_keeps_the_status_line(monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    read_end, write_end = os.pipe()
    frame = messages.PoseFrame(t=0.0, root_pos=np.zeros(3), rotations=np.tile([1.0, 0, 0, 0], (21, 1)))
    for seq in range(3):
        os.write(write_end, messages.encode_pose_frame(frame, seq))
    try:
        assert listen_plot_loop(Listener(fd=read_end), seconds=0.2) == 0
    finally:
        os.close(read_end)
        os.close(write_end)
    err = capsys.readouterr().err
    assert "no display" in err and "frames 3" in err


# --------------------------------------------------------------------------------------------------
# The page in a browser (optional: needs Chromium)

CHROMIUM = os.environ.get("CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")


def check_report(*args):
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "check-report"), *map(str, args)],
                          capture_output=True, text=True, timeout=120)


@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (apt-get install -y chromium) for scripts/check-report")
def test_report_page_opens_in_chromium_with_every_image_loaded(report, tmp_path):
    shot = tmp_path / "page.png"
    done = check_report(report, "--screenshot", str(shot))
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"{len(FIGURES)}/{len(FIGURES)} images loaded, 0 problem(s)" in done.stdout
    assert_picture(shot)

    # The check is not a rubber stamp: a missing picture fails it and is named.
    broken = tmp_path / "broken"
    shutil.copytree(report, broken)
    (broken / "ssi_timeline.png").unlink()
    done = check_report(broken)
    assert done.returncode == 1 and "image not loaded: ssi_timeline.png" in done.stdout


def test_the_health_timeline_has_no_corrupt_legend_when_nothing_was_corrupt(tmp_path, monkeypatch):
    """A legend entry for corrupt packets only when some were counted."""
    pytest.importorskip("matplotlib")
    from viz import canvas, figures
    labels = {}

    def keep(fig, path):
        labels[path.name if hasattr(path, "name") else path] = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
        return path
    monkeypatch.setattr(canvas, "save_png", keep)
    t = [0.1 * k for k in range(50)]
    base = {"t": t, "lost": {"waist": [0] * 20 + [1] * 10 + [0] * 20}, "faults": [{"t": 0.0, "kind": "noise"}]}
    figures.health_timeline({**base, "corrupt": [0] * 50}, tmp_path / "a.png")
    figures.health_timeline({**base, "corrupt": [0] * 49 + [3]}, tmp_path / "b.png")
    assert not any("corrupt" in x for x in labels["a.png"])
    assert any("corrupt" in x for x in labels["b.png"])


def test_a_replay_report_has_the_skeleton_pictures(tmp_path):
    """edge replay --report dumps the decoded poses beside the ground truth, and the report draws the
    skeleton strip and the animation from them (they were missing for replays)."""
    pytest.importorskip("matplotlib")
    from edgecli import main as edge_main
    out = tmp_path / "report"
    assert edge_main(["replay", str(ROOT / "samples" / "cmu_09_12_walk.session.npz"), "--speed", "max",
                      "--seconds", "4", "--json", str(tmp_path / "r.json"), "--report", str(out)]) == 0
    (dump,) = (out / "dump").glob("*.npz")
    d = np.load(dump)
    assert d["pred_pos"].shape == d["gt_pos"].shape and d["pred_pos"].shape[1:] == (21, 3)
    assert np.isfinite(d["pred_pos"]).all()
    page = (out / "index.html").read_text()
    assert '<img src="skeleton_strip.png"' in page and (out / "animation.gif").exists()
