"""int8 models: they load, stay close to fp32 on the bundled sample, and the manifest keeps the fp32 entries."""
import json
import shutil

import numpy as np
import pytest

from edge import quat
from motion.evaluate import evaluate
from edge.features import sequence_features
from edge.inference import Autoencoder, make_session, model_files
from edge.modelfiles import DEFAULT_DIR, ModelError, load_manifest, sha256, write_manifest
from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from edge.plausibility import PlausibilityScorer
from motion.takes import from_sample
from quantize.common import head_anchored_positions, rollout
from tests.conftest import SAMPLE

FP32 = ("decoder.onnx", "autoencoder.onnx", "decoder_jacobian.onnx")
INT8 = ("decoder.int8.onnx", "autoencoder.int8.onnx", "decoder_jacobian.int8.onnx")


@pytest.fixture(scope="module")
def manifest():
    m = json.loads((DEFAULT_DIR / "manifest.json").read_text())
    if not all(n in m["files"] for n in INT8):
        pytest.fail("models/manifest.json does not list the int8 models: run python -m quantize")
    return m


@pytest.fixture(scope="module")
def take():
    return from_sample(SAMPLE)


def test_manifest_lists_fp32_and_int8_and_the_int8_record_their_fp32_source(manifest):
    for name in FP32 + INT8:
        assert manifest["files"][name]["sha256"] == sha256(DEFAULT_DIR / name)
    for src, q in zip(FP32, INT8, strict=True):
        entry = manifest["files"][q]
        assert entry["source"] == src and entry["source_sha256"] == manifest["files"][src]["sha256"]
        assert entry["precision"] == "int8" and entry["method"] in ("dynamic", "static")
    for key in ("fps", "latent", "hidden", "features", "joint_names", "parents", "plausibility_threshold_m", "training"):
        assert key in manifest


def test_int8_decoder_is_at_most_40_percent_of_fp32():
    assert (DEFAULT_DIR / INT8[0]).stat().st_size <= 0.40 * (DEFAULT_DIR / FP32[0]).stat().st_size


def test_pipeline_loads_int8_models_and_poses_like_fp32(take, manifest):
    """The int8 pipeline runs the int8 files and its poses stay close to fp32's over the whole walk (16 s):
    each frame's worst joint within 2 cm on average and 5 cm in 95 % of frames. (Not every frame: the
    pipeline's discrete choices, a foot lock taken a frame earlier, turn millimetres into centimetres for
    a few frames; v0.3 reached 10.7 cm on one frame of this take, v0.4 7.7 cm, v0.5.1 15 cm. Each such
    event lasts 10-15 frames, so 5 s held only two of them under the 95 % line: v0.5.1's first 5 s gave
    p95 5.7 cm, the whole walk 2.4. The network alone is held to 3 cm at worst by the closed-loop test
    below.)"""
    pipe = Pipeline(PipelineOptions(samples=4, precision="int8", ssi=False))
    ref = Pipeline(PipelineOptions(samples=4, precision="fp32", ssi=False))
    assert pipe.manifest["files_in_use"] == list(model_files("int8", manifest)) and pipe.precision == "int8"
    assert model_files("int8", manifest)[0] == INT8[0]      # the int8 decoder always; the autoencoder as measured
    worst = []
    for t in range(take.frames):
        a, b = pipe.step(take.signals.slice(t, t + 1)), ref.step(take.signals.slice(t, t + 1))
        if a is not None:
            worst.append(float(np.linalg.norm(a.positions - b.positions, axis=-1).max()))
    assert min(worst) >= 0.0 and max(worst) > 0.0          # different (int8 did run)
    assert np.mean(worst) < 0.02 and np.percentile(worst, 95) < 0.05


def test_int8_decoder_tracks_fp32_in_closed_loop_on_the_sample(take, manifest):
    """Both decoders fed their own GRU state for the whole take (959 frames) at the prior mean.

    Tolerances: rot6d within 0.05 and FK joint positions within 0.5 cm on average and 3 cm at worst
    (measured: 0.020, 0.19 cm and 1.0 cm)."""
    f, _, yaw = sequence_features(take.signals, take.fps, n_features=manifest["features"])
    root = quat.to_matrix(quat.mul(quat.inv(yaw), take.signals.waist_rot))[:, None]
    feats, z = f[:, None].astype(np.float32), np.zeros((1, 30), np.float32)
    a = rollout(make_session(DEFAULT_DIR / FP32[0]), feats, z)[0]
    b = rollout(make_session(DEFAULT_DIR / INT8[0]), feats, z)[0]
    d = np.linalg.norm(head_anchored_positions(a, root) - head_anchored_positions(b, root), axis=-1)
    assert np.abs(a - b).max() < 0.05
    assert d.mean() < 0.005 and d.max() < 0.03


def test_int8_autoencoder_scores_the_sample_like_fp32(take, manifest):
    """Plausibility scores of the sample's ground-truth poses within 1 cm (mean) and the same verdicts."""
    th = manifest["plausibility_threshold_m"]
    pos = take.gt_pos[::4]
    pelvis = quat.to_matrix(take.signals.waist_rot[::4])
    s32 = PlausibilityScorer(Autoencoder(make_session(DEFAULT_DIR / FP32[1])), th).lower_body_error(pos, pelvis)
    s8 = PlausibilityScorer(Autoencoder(make_session(DEFAULT_DIR / INT8[1])), th).lower_body_error(pos, pelvis)
    assert np.abs(s8 - s32).mean() < 0.01
    assert np.array_equal(s8 > th, s32 > th)


def test_int8_eval_on_the_sample_is_within_2_percent_of_fp32(manifest):
    r = {p: evaluate([SAMPLE], PipelineOptions(precision=p), log=lambda *_: None) for p in ("fp32", "int8")}
    assert r["int8"]["mpjpe_cm"] <= 1.02 * r["fp32"]["mpjpe_cm"]


# ---------------------------------------------------------------------------------------------- the tool

@pytest.fixture
def model_copy(tmp_path):
    pytest.importorskip("onnx", reason="quantizing needs the onnx package")
    for name in FP32 + ("manifest.json",):
        shutil.copyfile(DEFAULT_DIR / name, tmp_path / name)
    return tmp_path


def test_quantize_adds_int8_entries_keeps_everything_else_and_reruns_identically(model_copy, monkeypatch):
    """The files and the manifest, not the timings: those are fixed here (int8 decoder 0.5x fp32, int8
    autoencoder 1.5x), because v0.4's int8 autoencoder times at about 1.2x fp32 here, on the hysteresis
    line, and a busy machine moved it across between two builds (6 runs of this test under load, one
    flip). The runtime choice's rule has its own test below."""
    import quantize.build as qb
    from quantize.build import build
    fixed = lambda path, rows, frames=0, warmup=0: {"p50": 100.0 * (       # noqa: E731
        (0.5 if "decoder" in str(path) else 1.5) if ".int8" in str(path) or "dynamic" in str(path) else 1.0)}
    monkeypatch.setattr(qb, "autoencoder_call_us", fixed)
    monkeypatch.setattr(qb, "decoder_call_us", fixed)
    before = json.loads((model_copy / "manifest.json").read_text())
    build(model_copy, data=None, methods=("dynamic",), log=lambda *_: None)
    after = json.loads((model_copy / "manifest.json").read_text())
    for name in FP32:
        assert after["files"][name] == before["files"][name]
    rest = lambda m: {k: v for k, v in m.items() if k not in ("files", "precisions")}    # noqa: E731
    assert rest(after) == rest(before)
    assert all(n in after["files"] for n in INT8)
    assert after["precisions"]["int8"]["decoder"] == INT8[0]        # which autoencoder: as measured
    load_manifest(model_copy, need=INT8)                       # verifies the sha256 of the new files
    build(model_copy, data=None, methods=("dynamic",), log=lambda *_: None)
    again = json.loads((model_copy / "manifest.json").read_text())
    assert again == after                                      # deterministic: re-running changes nothing


def test_a_rebuild_keeps_the_earlier_runtime_choice_unless_the_times_clearly_disagree(model_copy, monkeypatch):
    """int8 at 1.15x fp32 is near the 1.1x line: a rebuild keeps whichever file the folder ran before
    (an fp32 choice flips to int8 only at <= 1.0x, an int8 one to fp32 only above 1.2x), so a busy
    machine cannot flip it between two runs; at 1.3x the int8 choice does go."""
    import quantize.build as qb
    ratio = {"x": 1.15}
    fake = lambda path, rows, frames=0, warmup=0: {"p50": 100.0 * (ratio["x"] if ".int8" in str(path) or      # noqa: E731
                                                                   "dynamic" in str(path) else 1.0)}
    monkeypatch.setattr(qb, "autoencoder_call_us", fake)
    monkeypatch.setattr(qb, "decoder_call_us", fake)

    def rebuild_after(choice):
        m = json.loads((model_copy / "manifest.json").read_text())
        m.setdefault("precisions", {}).setdefault("int8", {})["autoencoder"] = choice
        (model_copy / "manifest.json").write_text(json.dumps(m))
        qb.build(model_copy, data=None, methods=("dynamic",), log=lambda *_: None)
        return json.loads((model_copy / "manifest.json").read_text())["precisions"]["int8"]["autoencoder"]

    assert rebuild_after("autoencoder.onnx") == "autoencoder.onnx"
    assert rebuild_after("autoencoder.int8.onnx") == "autoencoder.int8.onnx"
    ratio["x"] = 1.3
    assert rebuild_after("autoencoder.int8.onnx") == "autoencoder.onnx"
    ratio["x"] = 0.95
    assert rebuild_after("autoencoder.onnx") == "autoencoder.int8.onnx"


def test_after_an_fp32_reexport_int8_is_refused_until_quantize_runs_again(model_copy):
    from quantize.build import build
    build(model_copy, data=None, methods=("dynamic",), log=lambda *_: None)
    info = {k: v for k, v in json.loads((model_copy / "manifest.json").read_text()).items() if k != "files"}
    write_manifest(model_copy, list(FP32), info)               # what models.export does
    with pytest.raises(ModelError, match="quantize"):
        load_manifest(model_copy, need=INT8)
    build(model_copy, data=None, methods=("dynamic",), log=lambda *_: None)
    load_manifest(model_copy, need=FP32 + INT8)


def test_quantize_refuses_an_fp32_file_that_does_not_match_the_manifest(model_copy):
    from quantize.build import build
    with open(model_copy / "decoder.onnx", "ab") as f:
        f.write(b"\0")
    with pytest.raises(ModelError, match="does not match"):
        build(model_copy, data=None, methods=("dynamic",), log=lambda *_: None)


def test_the_layers_that_read_normalised_inputs_stay_fp32_in_the_int8_builds():
    """The export folds the input normalisation into the first layers (1/std per input column); per-channel
    int8 cannot hold columns 1000x apart, so quantize leaves those layers fp32."""
    pytest.importorskip("onnx", reason="reading the graphs needs the onnx package")
    import onnx
    from quantize.build import head_layers, input_layers
    layers = input_layers(DEFAULT_DIR / "decoder.onnx")   # the CVAE's first layer (both parts), the head's (v0.5)
    assert layers[:2] == ["/fc_features/Gemm", "/fc_latent/Gemm"] and all(n.startswith("/upper/") for n in layers[2:])
    assert set(layers[2:]) <= set(head_layers(DEFAULT_DIR / "decoder.onnx"))
    assert input_layers(DEFAULT_DIR / "autoencoder.onnx") == ["/net/net.0/Gemm"]
    int8 = onnx.load(str(DEFAULT_DIR / INT8[0])).graph
    kept = [n for n in int8.node if n.name.startswith(("/fc_", "/upper/"))]     # the head stays fp32 whole
    assert kept and all(n.op_type in ("Gemm", "Relu", "Slice", "Constant") for n in kept)
    assert any(n.op_type in ("DynamicQuantizeMatMul", "MatMulInteger", "MatMulIntegerToFloat") for n in int8.node)


def test_the_int8_decoder_keeps_its_fp32_layers_as_single_gemms():
    """quantize_dynamic splits every Gemm into MatMul + Add, and ORT fuses the pair back only where the Add's
    other input is a constant bias; a Gemm whose C is a tensor (the frame's shared feature part, the 6D the
    head adds to) would stay two nodes and its ReLU a third. quantize.build.gemms_back puts them back."""
    pytest.importorskip("onnx", reason="reading the graphs needs the onnx package")
    import onnx
    from quantize.build import head_layers, input_layers
    kept = set(input_layers(DEFAULT_DIR / "decoder.onnx") + head_layers(DEFAULT_DIR / "decoder.onnx"))
    int8 = {n.name: n for n in onnx.load(str(DEFAULT_DIR / INT8[0])).graph.node}
    split = sorted(name for name in kept if getattr(int8.get(name), "op_type", None) != "Gemm")
    assert split == [], f"fp32 layers left as MatMul + Add: {split}"
    with_c = [int8[n] for n in ("/fc_latent/Gemm", "/upper/first_r/Gemm", "/upper/out/Gemm")]
    assert all(n.input[2].endswith("_output_0") for n in with_c)        # C a tensor the graph makes
