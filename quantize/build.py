"""int8 builds of the shipped fp32 models, the choice between quantization methods, and the manifest.

Candidates for each model:
- `dynamic`: onnxruntime.quantization.quantize_dynamic, per-channel symmetric QInt8 weights in 7 bits
  (REDUCE_RANGE); activations quantized per call (u8) -> MatMulInteger. Needs no data.
- `static`: quantize_static, QDQ format, per-channel QInt8 weights and u8 activations calibrated
  (MinMax) on real `train` inputs: the decoder's features, latents as SSI draws them and the GRU states
  a closed-loop fp32 rollout produces; the autoencoder's ground-truth poses. Only Gemm/MatMul are
  quantized (the gates' Sigmoid/Tanh and the adds stay fp32).

Each candidate is measured against fp32 on held-out `val` windows (closed-loop decoder rollouts,
FK joint positions; autoencoder plausibility scores) and the most accurate is kept; the decoder also
has to be no slower than fp32 at N=100. Without the mocap data only `dynamic` can be built.
"""
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from edge.inference import make_session
from edge.int8check import BOUNDS, REFERENCE
from edge.modelfiles import JACOBIAN, ModelError, add_to_manifest, read_manifest, sha256
from quantize.common import (MODELS, autoencoder_call_us, decoder_call_us, fp32_name, head_anchored_positions,
                             int8_name, jacobian_call_us, latents_for, mocap_windows, rollout)

CALIB_WINDOWS, CALIB_FRAMES, CALIB_LATENTS = 48, 120, 2
# 7-bit weights: ONNX Runtime's u8 x s8 kernel on x86 without VNNI (VPMADDUBSW) sums pairs of products in
# 16 bits, which 8-bit weights can saturate (255 * 127 * 2 > 32767) and 7-bit ones cannot (255 * 63 * 2);
# VNNI and ARM accumulate in 32 bits. With 7 bits every CPU computes the same integers: the int8 files
# give one body everywhere (models/MODEL_CARD.md, "int8 on every CPU", has what each scheme costs).
REDUCE_RANGE = True
VAL_WINDOWS, VAL_FRAMES, VAL_LATENTS = 48, 240, 2


def _quiet_quantizer_logs():
    import logging
    logging.getLogger().setLevel(logging.ERROR)   # "please run pre-processing" goes through the root logger


NORMALISED_INPUTS = ("features", "positions")     # the inputs models.nets normalises (decoder, autoencoder)
# The decoder's first layer is two (models.nets.DecoderStep: the features' part runs once a frame); its
# latent part stays fp32 as the whole layer always was, so the split leaves the int8 build's function.
FP32_INPUTS = NORMALISED_INPUTS + ("latent",)


def input_layers(path):
    """Names of the Gemm/MatMul nodes that read a normalised model input (directly or through a Concat or
    a Slice: the CVAE and the upper-body head each read their columns of `features`), and the decoder's
    latent part of its first layer (FP32_INPUTS).

    They stay fp32: the export folds the input normalisation into their weights (models.nets), which
    scales each input column by 1/std. One per-channel int8 scale per output row cannot cover columns
    that differ by 1000x; quantized, these layers doubled the decoder's closed-loop error."""
    import onnx
    g = onnx.load(str(path)).graph
    inputs = {i.name for i in g.input} & set(FP32_INPUTS)
    made_by = {o: n for n in g.node for o in n.output}

    def reads_input(name):
        n = made_by.get(name)
        return name in inputs or (n is not None and n.op_type in ("Concat", "Slice") and any(reads_input(i) for i in n.input))

    return [n.name for n in g.node if n.op_type in ("Gemm", "MatMul") and reads_input(n.input[0])]


def head_layers(path):
    """The upper-body head's Gemm nodes (models.nets.UpperBodyStep). They stay fp32 too: the head reads the
    CVAE's 6D through a folded normalisation as uneven as the features' (some 6D columns hardly move), and
    in int8 it moved the closed-loop body by 7.7 cm on average; it is 28 k weights, a few us at N=16."""
    import onnx
    return [n.name for n in onnx.load(str(path)).graph.node
            if n.op_type in ("Gemm", "MatMul") and n.name.startswith("/upper/")]


def quantize_dynamic_model(src, dst):
    from onnxruntime.quantization import QuantType, quantize_dynamic
    _quiet_quantizer_logs()
    # quantize_dynamic first rewrites each Gemm as a MatMul named <gemm>_MatMul and matches that name.
    kept = input_layers(src) + head_layers(src)
    keep = [n + suffix for n in kept for suffix in ("", "_MatMul")]
    quantize_dynamic(str(src), str(dst), weight_type=QuantType.QInt8, per_channel=True, reduce_range=REDUCE_RANGE,
                     nodes_to_exclude=keep)
    gemms_back(dst, kept)


def gemms_back(path, gemms):
    """Undo quantize_dynamic's rewrite of the fp32 Gemms it leaves (each became <gemm>_MatMul + <gemm>_Add).

    ORT fuses a MatMul and an Add of a constant bias back into a Gemm, but not one whose C is a tensor
    (models.nets: the first layers' features part, which the frame's rows share, comes in as Gemm's C):
    those stay two nodes and their ReLU a third, about 0.6 us each at N=16. Rewritten in place."""
    import onnx
    model = onnx.load(str(path))
    g = model.graph
    by_name = {n.name: n for n in g.node}
    changed = False
    for name in dict.fromkeys(gemms):
        mm, add = by_name.pop(name + "_MatMul", None), by_name.pop(name + "_Add", None)
        if mm is None or add is None or mm.op_type != "MatMul" or add.op_type != "Add" or mm.output[0] not in add.input:
            continue
        c = add.input[1] if add.input[0] == mm.output[0] else add.input[0]
        gemm = onnx.helper.make_node("Gemm", [mm.input[0], mm.input[1], c], [add.output[0]], name=name)
        at = list(g.node).index(mm)
        g.node.remove(mm)
        g.node.remove(add)
        g.node.insert(at, gemm)
        changed = True
    if changed:
        onnx.checker.check_model(model)
        onnx.save(model, str(path))


class _Reader:
    """CalibrationDataReader over a list of input dicts."""

    def __init__(self, batches):
        self._it = iter(batches)

    def get_next(self):
        return next(self._it, None)

    def rewind(self):  # some onnxruntime versions call it
        pass


def quantize_static_model(src, dst, batches):
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    _quiet_quantizer_logs()
    with tempfile.TemporaryDirectory() as tmp:   # the calibrator writes an augmented model next to its cwd
        cwd = os.getcwd()
        os.chdir(tmp)
        try:
            quantize_static(str(Path(cwd, src)), str(Path(cwd, dst)), _Reader(batches), quant_format=QuantFormat.QDQ,
                            op_types_to_quantize=["Gemm", "MatMul"], nodes_to_exclude=input_layers(src) + head_layers(src),
                            per_channel=True, reduce_range=REDUCE_RANGE,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                            calibrate_method=CalibrationMethod.MinMax)
        finally:
            os.chdir(cwd)


# ---------------------------------------------------------------------------------------------- data

def _rows(win, latents):
    """Repeat each window's features for every latent: [T,Wn,F] -> [T,Wn*K,F]; latents tiled to match."""
    K = len(latents)
    feats = np.repeat(win["features"], K, axis=1)
    z = np.tile(latents, (win["features"].shape[1], 1))
    return feats, z


def decoder_calibration(fp32_path, train):
    """Decoder inputs as the runtime sees them: one dict per frame of a closed-loop fp32 rollout."""
    feats, z = _rows(train, latents_for(CALIB_LATENTS, seed=1))
    _, _, hidden = rollout(make_session(fp32_path), feats, z)
    return [{"features": feats[t], "latent": z, "hidden": hidden[t]} for t in range(len(feats))]


def autoencoder_calibration(train):
    pos = train["poses"]["positions"]
    return [{"positions": pos[i:i + 256]} for i in range(0, len(pos), 256)]


# ---------------------------------------------------------------------------------------------- measures

def measure_decoder(path, ref_path, val, ref=None):
    """Closed-loop rollouts on val windows against fp32: FK joint positions and rot6d, and MPJPE against
    ground truth at the prior mean (the training metric: head-anchored, no IK)."""
    feats, z = _rows(val, latents_for(VAL_LATENTS, seed=2))
    K = VAL_LATENTS
    root = np.repeat(val["root_rot"], K, axis=1)
    if ref is None:
        r6, _, _ = rollout(make_session(ref_path), feats, z)
        ref = {"rot6d": r6, "pos": head_anchored_positions(r6, root)}
    r6, _, _ = rollout(make_session(path), feats, z)
    pos = head_anchored_positions(r6, root)
    d = np.linalg.norm(pos - ref["pos"], axis=-1)                     # [T,B,J] metres
    gt = np.repeat(val["gt_rel"], K, axis=1)
    mean_rows = np.arange(0, feats.shape[1], K)                       # the z = 0 rows
    mpjpe = np.linalg.norm(pos[:, mean_rows] - gt[:, mean_rows], axis=-1).mean()
    return ref, {"fk_pos_dev_mean_cm": float(d.mean() * 100), "fk_pos_dev_max_cm": float(d.max() * 100),
                 "rot6d_dev_max": float(np.abs(r6 - ref["rot6d"]).max()),
                 "val_mpjpe_no_ik_cm": float(mpjpe * 100)}


def measure_autoencoder(path, ref_path, val, threshold):
    from edge.inference import Autoencoder
    from edge.plausibility import PlausibilityScorer
    from edge.skeleton import NUM_JOINTS
    poses = val["poses"]
    # The scorer takes world positions and the pelvis rotation; the pose batch is already in the
    # character frame with the pelvis at the origin's XZ, so it passes through local_pose unchanged.
    pos = poses["positions"].reshape(-1, NUM_JOINTS, 3).astype(np.float64)
    rot = poses["root_rot"].astype(np.float64)
    s_ref = PlausibilityScorer(Autoencoder(make_session(ref_path)), threshold).lower_body_error(pos, rot)
    s = PlausibilityScorer(Autoencoder(make_session(path)), threshold).lower_body_error(pos, rot)
    d = np.abs(s - s_ref)
    return {"score_dev_mean_cm": float(d.mean() * 100), "score_dev_max_cm": float(d.max() * 100),
            "flag_agreement": float(np.mean((s > threshold) == (s_ref > threshold))),
            "implausible_rate_fp32": float(np.mean(s_ref > threshold)), "implausible_rate": float(np.mean(s > threshold))}


def write_int8_reference(folder, frames=240, rows=4, poses=240):
    """The self-check's reference input (edge.int8check), from the bundled walk (never trained on):
    its first `frames` frames of decoder features for `rows` latents (the prior mean and SSI-like draws),
    the waist rotation for FK, and `poses` of its ground-truth poses for the autoencoder."""
    from edge import quat
    from edge.features import sequence_features
    from motion.takes import from_sample
    manifest = read_manifest(folder)
    take = from_sample(Path(__file__).resolve().parent.parent / "samples" / "cmu_09_12_walk.npz")
    f, _, yaw = sequence_features(take.signals, take.fps, n_features=manifest["features"])
    rng = np.random.default_rng(7)
    latent = np.concatenate([np.zeros((1, manifest["latent"])), 0.7 * rng.standard_normal((rows - 1, manifest["latent"]))])
    step = max(1, len(take.gt_pos) // poses)
    np.savez_compressed(
        Path(folder) / REFERENCE,
        features=np.ascontiguousarray(np.repeat(f[:frames, None], rows, axis=1), np.float32),
        latent=latent.astype(np.float32),
        root_rot=quat.to_matrix(quat.mul(quat.inv(yaw), take.signals.waist_rot))[:frames].astype(np.float32),
        poses=take.gt_pos[::step][:poses], pelvis_rot=quat.to_matrix(take.signals.waist_rot[::step][:poses]))


# ---------------------------------------------------------------------------------------------- manifest

def check_sources(folder):
    """The fp32 files must match the manifest (the int8 builds record which fp32 file they came from)."""
    manifest = read_manifest(folder)
    out = {}
    for m in MODELS:
        name = fp32_name(m)
        entry = manifest["files"].get(name)
        if entry is None or not (Path(folder) / name).exists():
            raise ModelError(f"{folder}/{name} is missing or not in the manifest: export the fp32 models first")
        digest = sha256(Path(folder) / name)
        if digest != entry["sha256"]:
            raise ModelError(f"{folder}/{name} does not match manifest.json (sha256 {digest[:12]}...): "
                             f"re-export (python -m models.export) or restore it before quantizing")
        out[name] = digest
    return manifest, out


# ---------------------------------------------------------------------------------------------- build

def build_jacobian(folder, tmp, entries, report, log, decoder_int8=True):
    """The refiner's batch graph (models.nets.JacobianStep, the decoder's weights) in dynamic int8, as
    the decoder's dynamic build. The int8 runtime opens it when it opens the int8 decoder
    (`decoder_int8`; a choice made from timings here would flip with a busy machine); its time against
    fp32 on the refiner's 32 rows (best of 5 turns) goes in the report. Returns the file the int8
    runtime opens; the int8 file joins `entries`."""
    src, name = folder / JACOBIAN, int8_name(Path(JACOBIAN).stem)
    quantize_dynamic_model(src, tmp / name)
    turns = {"fp32": [], "int8": []}
    for _ in range(5):
        turns["fp32"].append(jacobian_call_us(src, 32, frames=150, warmup=20)["p50"])
        turns["int8"].append(jacobian_call_us(tmp / name, 32, frames=150, warmup=20)["p50"])
    best = {k: min(v) for k, v in turns.items()}
    chosen = name if decoder_int8 else JACOBIAN
    report["selection"]["jacobian_runtime"] = {
        "file": chosen, "why": f"as the decoder ({'int8' if decoder_int8 else 'fp32'}); int8 {best['int8']:.1f} us vs "
                               f"fp32 {best['fp32']:.1f} us per call on 32 rows (best of 5 turns)"}
    log(f"  jacobian: int8 {best['int8']:.1f} us, fp32 {best['fp32']:.1f} us on 32 rows: the int8 runtime opens {chosen}")
    shutil.copyfile(tmp / name, folder / name)
    entries[name] = {"precision": "int8", "method": "dynamic", "source": JACOBIAN,
                     "source_sha256": sha256(src)}
    return chosen


def build_jacobian_only(folder, log=print):
    """build_jacobian alone, for models whose decoder and autoencoder builds are already there."""
    folder = Path(folder)
    if JACOBIAN not in read_manifest(folder)["files"]:
        raise ModelError(f"{folder}/manifest.json does not list {JACOBIAN}: "
                         f"python -m models.export --ckpt {folder}/checkpoints --out {folder} --jacobian-only")
    report, entries = {"selection": {}}, {}
    with tempfile.TemporaryDirectory(prefix="quantize-") as tmp:
        precisions = read_manifest(folder).get("precisions", {}).get("int8", {})
        runtime = build_jacobian(folder, Path(tmp), entries, report, log,
                                 decoder_int8=precisions.get("decoder", int8_name("decoder")) == int8_name("decoder"))
    add_to_manifest(folder, entries, {"int8": {**precisions, "jacobian": runtime}})
    report["files"] = {k: read_manifest(folder)["files"][k] for k in entries}
    return report


def build(folder, data=None, methods=("dynamic", "static"), log=print):
    """Build models/{decoder,autoencoder}.int8.onnx and add them to the manifest. Returns a report dict."""
    folder = Path(folder).resolve()         # the static calibrator runs in a folder of its own
    manifest, digests = check_sources(folder)
    have_data = data is not None and (Path(data) / "MANIFEST.tsv").exists()
    if not have_data and "static" in methods:
        log(f"no mocap data at {data}: static calibration skipped, building dynamic int8 only")
        methods = tuple(m for m in methods if m != "static")
    if not methods:
        raise SystemExit("quantize: nothing to build")
    windows = None
    if have_data:
        log("calibration and validation windows from the mocap data (train / val) ...")
        windows = (mocap_windows(data, "train", CALIB_WINDOWS, CALIB_FRAMES, seed=11, n_features=manifest["features"]),
                   mocap_windows(data, "val", VAL_WINDOWS, VAL_FRAMES, seed=12, n_features=manifest["features"]))
    report = {"methods_tried": list(methods), "selection": {}, "candidates": {}}
    entries, runtime = {}, {}
    earlier = manifest.get("precisions", {}).get("int8", {})      # the runtime files a previous build chose
    with tempfile.TemporaryDirectory(prefix="quantize-") as tmp:
        tmp = Path(tmp)
        for model in MODELS:
            src = folder / fp32_name(model)
            report[f"{model}_fp32_call_us_n100"] = fp32_us = call_us(model, src, 100)["p50"]
            cands = build_candidates(model, src, tmp, methods, windows and windows[0], log)
            if have_data:
                chosen, why = choose_candidate(model, src, tmp, methods, cands, windows[1], manifest, report, fp32_us, log)
            else:
                chosen, why = "dynamic", "no calibration data: dynamic is the only candidate"
            runtime[model] = runtime_file(model, src, tmp / f"{model}.{chosen}.onnx", earlier, report)
            report["candidates"][model] = cands
            report["selection"][model] = {"method": chosen, "why": why}
            log(f"  {model}: keeping {chosen} ({why})")
            out = folder / int8_name(model)
            part = out.with_name(out.name + ".tmp")
            shutil.copyfile(tmp / f"{model}.{chosen}.onnx", part)
            os.replace(part, out)
            entries[int8_name(model)] = {"precision": "int8", "method": chosen, "source": fp32_name(model),
                                         "source_sha256": digests[fp32_name(model)]}
        if JACOBIAN in manifest["files"]:
            runtime["jacobian"] = build_jacobian(folder, tmp, entries, report, log,
                                                 decoder_int8=runtime["decoder"] == int8_name("decoder"))
    write_int8_reference(folder)
    entries[REFERENCE] = {"purpose": "the runtime's int8 self-check input (edge.int8check)", "bounds": BOUNDS}
    add_to_manifest(folder, entries, {"int8": runtime})
    report["precisions"] = {"int8": runtime}
    report["files"] = {k: read_manifest(folder)["files"][k] for k in entries}
    return report


def call_us(model, path, n, **kw):
    """The call-time figures of `model`'s ONNX file at `path` with n rows (quantize.common)."""
    return (decoder_call_us if model == "decoder" else autoencoder_call_us)(path, n, **kw)


def build_candidates(model, src, tmp, methods, train, log):
    """Each method's int8 build of `src` in tmp/{model}.{method}.onnx, with its size and call time."""
    cands = {}
    for method in methods:
        dst = tmp / f"{model}.{method}.onnx"
        if method == "dynamic":
            quantize_dynamic_model(src, dst)
        else:
            calib = decoder_calibration(src, train) if model == "decoder" else autoencoder_calibration(train)
            quantize_static_model(src, dst, calib)
        cands[method] = {"bytes": dst.stat().st_size, "size_vs_fp32": dst.stat().st_size / src.stat().st_size,
                         "call_us_n100": call_us(model, dst, 100)["p50"]}
        log(f"  {model} {method}: {cands[method]['bytes']:,} bytes ({cands[method]['size_vs_fp32']:.1%} of fp32)")
    return cands


def choose_candidate(model, src, tmp, methods, cands, val, manifest, report, fp32_us, log):
    """The candidate closest to fp32 on val (the decoder's among those no slower than fp32): (method, why)."""
    ref = None
    for method in methods:
        p = tmp / f"{model}.{method}.onnx"
        if model == "decoder":
            ref, m = measure_decoder(p, src, val, ref)
        else:
            m = measure_autoencoder(p, src, val, manifest["plausibility_threshold_m"])
        cands[method].update(m)
        log(f"  {model} {method}: " + ", ".join(f"{k} {v:.4g}" for k, v in m.items()))
    if model == "decoder":
        report["decoder_fp32_val_mpjpe_no_ik_cm"] = measure_decoder(src, src, val, ref)[1]["val_mpjpe_no_ik_cm"]
        ok = [k for k in methods if cands[k]["call_us_n100"] <= 1.1 * fp32_us] or list(methods)
        return (min(ok, key=lambda k: cands[k]["fk_pos_dev_mean_cm"]),
                "smallest closed-loop FK deviation from fp32 on val among candidates no slower than fp32 at N=100")
    return (min(methods, key=lambda k: cands[k]["score_dev_mean_cm"]),
            "smallest plausibility-score deviation from fp32 on val poses")


def runtime_file(model, src, int8, earlier, report):
    """The file the int8 runtime opens for `model`: the int8 build unless it is clearly slower than fp32
    here (a 7-layer MLP as small as the autoencoder is all per-node overhead, and int8 adds quantize
    nodes). Timed in turns, best of 5 turns each. A rebuild keeps the folder's earlier choice unless the
    times clearly say otherwise (hysteresis: int8 at <= 1.0x fp32 over an fp32 choice, fp32 at > 1.2x
    over an int8 one), so a busy machine near the 1.1x line does not flip it."""
    turns = {k: [] for k in ("fp32", "int8")}
    for _ in range(5):
        turns["fp32"].append(call_us(model, src, 100, frames=150, warmup=20)["p50"])
        turns["int8"].append(call_us(model, int8, 100, frames=150, warmup=20)["p50"])
    best = {k: min(v) for k, v in turns.items()}
    line = {int8_name(model): 1.2, fp32_name(model): 1.0}.get(earlier.get(model), 1.1)
    chosen = int8_name(model) if best["int8"] <= line * best["fp32"] else fp32_name(model)
    report["selection"][model + "_runtime"] = {
        "file": chosen, "why": f"int8 {best['int8']:.1f} us vs fp32 {best['fp32']:.1f} us per call at N=100 (best of 5 turns)"}
    return chosen
