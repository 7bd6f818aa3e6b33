"""Start-up self-check: does this CPU's int8 give the body the model card promises?

ONNX Runtime's int8 kernels differ by processor: x86 without VNNI multiplies u8 x s8 with VPMADDUBSW,
whose 16-bit pair sums saturate for 8-bit weights; VNNI and ARM cores accumulate in 32 bits. The
shipped int8 files use 7-bit weights (quantize.build: reduce_range), for which no kernel saturates, but
a board nobody here tested may still disagree. So before the first frame the runtime runs the int8 and
fp32 models once on a stored reference input (`int8_check.npz`, listed in the manifest with its sha256
and the card's bounds) and compares:
- the decoder: a closed-loop rollout (each step fed the GRU state it wrote) of the reference frames and
  latents; the worst head-anchored FK joint deviation between the two;
- the autoencoder: plausibility scores of the reference poses; the mean deviation and whether every
  verdict (above / below the threshold) is the same.
If int8 is beyond a bound, the runtime uses fp32 and says so (`precision fp32 (int8 off on this CPU: ...)`).
"""
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from edge import quat
from edge.skeleton import HEAD, NUM_JOINTS, NUM_PREDICTED, fk

REFERENCE = "int8_check.npz"
# The model card's bounds (models/MODEL_CARD.md, "int8 on every CPU"): what int8 may differ from fp32.
BOUNDS = {"decoder_fk_max_cm": 3.0, "autoencoder_score_mean_cm": 1.0, "verdicts_same_min": 0.99}


@dataclass(frozen=True)
class Int8Check:
    ok: bool
    decoder_fk_max_cm: float
    autoencoder_score_mean_cm: float
    verdicts_same: float
    why: str            # the first bound int8 broke, '' when it kept them all

    def as_dict(self):
        return asdict(self)


def head_anchored_positions(rot6d, root_rot):
    """The decoder's rot6d [...,120] under the waist rotation [...,3,3] -> joint positions with the head
    joint at the origin [...,J,3] (the training metric's frame)."""
    lead = rot6d.shape[:-1]
    local = np.empty(lead + (NUM_JOINTS, 3, 3))
    local[..., 0, :, :] = root_rot
    local[..., 1:, :, :] = quat.matrix_from_6d(rot6d.reshape(lead + (NUM_PREDICTED, 6)).astype(np.float64))
    _, pos = fk(local, np.zeros(lead + (3,)))
    return pos - pos[..., HEAD:HEAD + 1, :]


def rollout(session, features, latent):
    """Closed-loop rollout: features [T,R,F], latent [R,L] -> rot6d [T,R,120]."""
    T, R, _ = features.shape
    width = {i.name: i.shape for i in session.get_inputs()}["hidden"][1]
    h = np.zeros((R, width), np.float32)
    out = np.empty((T, R, 6 * NUM_PREDICTED), np.float32)
    for t in range(T):
        out[t], _, h = session.run(None, {"features": features[t], "latent": latent, "hidden": h})
    return out


def compare(int8, fp32, reference, threshold, bounds=None):
    """int8 and fp32 sessions {"decoder": .., "autoencoder": ..} on the reference arrays -> Int8Check."""
    from edge.inference import Autoencoder
    from edge.plausibility import PlausibilityScorer
    bounds = {**BOUNDS, **(bounds or {})}
    feats, latent, root = reference["features"], reference["latent"], reference["root_rot"]
    root = np.broadcast_to(root[:, None].astype(np.float64), feats.shape[:2] + (3, 3))
    pos = {k: head_anchored_positions(rollout(s["decoder"], feats, latent), root) for k, s in
           (("int8", int8), ("fp32", fp32))}
    fk_max = float(np.linalg.norm(pos["int8"] - pos["fp32"], axis=-1).max() * 100)
    poses, pelvis = reference["poses"].astype(np.float64), reference["pelvis_rot"].astype(np.float64)
    score = {k: PlausibilityScorer(Autoencoder(s["autoencoder"]), threshold).lower_body_error(poses, pelvis)
             for k, s in (("int8", int8), ("fp32", fp32))}
    score_mean = float(np.abs(score["int8"] - score["fp32"]).mean() * 100)
    same = float(np.mean((score["int8"] > threshold) == (score["fp32"] > threshold)))
    why = ""
    if not fk_max <= bounds["decoder_fk_max_cm"]:
        why = f"decoder FK {fk_max:.2f} cm from fp32, bound {bounds['decoder_fk_max_cm']:g}"
    elif not score_mean <= bounds["autoencoder_score_mean_cm"]:
        why = f"plausibility scores {score_mean:.2f} cm from fp32, bound {bounds['autoencoder_score_mean_cm']:g}"
    elif not same >= bounds["verdicts_same_min"]:
        why = f"plausibility verdicts {100 * same:.1f} % the same as fp32's, bound {100 * bounds['verdicts_same_min']:g} %"
    return Int8Check(not why, fk_max, score_mean, same, why)


def read_reference(path):
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in ("features", "latent", "root_rot", "poses", "pelvis_rot")}


@lru_cache(maxsize=8)
def _check_cached(folder, int8_files, fp32_files, digests, threshold, bounds):
    from edge.inference import make_session
    del digests             # part of the key only: a rebuilt file is checked again
    reference = read_reference(Path(folder) / REFERENCE)
    sessions = {p: {m: make_session(Path(folder) / f) for m, f in zip(("decoder", "autoencoder"), files, strict=True)}
                for p, files in (("int8", int8_files), ("fp32", fp32_files))}
    return compare(sessions["int8"], sessions["fp32"], reference, threshold, dict(bounds))


def check_folder(manifest, folder, int8_files, fp32_files):
    """The self-check of a verified manifest's int8 files against its fp32 ones, once per process per
    set of files; None when the folder has no reference input (a folder built before the check)."""
    entry = manifest["files"].get(REFERENCE)
    if entry is None:
        return None
    digests = tuple(manifest["files"][f]["sha256"] for f in int8_files + fp32_files + (REFERENCE,))
    bounds = tuple(sorted(entry.get("bounds", {}).items()))
    return _check_cached(str(folder), tuple(int8_files), tuple(fp32_files), digests,
                         float(manifest["plausibility_threshold_m"]), bounds)


def main(argv=None):
    """python -m edge.int8check [MODELS]: the check of a folder's int8 files (decoder.int8.onnx and
    autoencoder.int8.onnx, whichever the runtime opens) against its fp32 ones on this CPU, as one JSON
    line; exit status 1 when int8 breaks a bound (scripts/int8-cpu-check, scripts/arm64-check)."""
    import json
    import sys
    from edge.inference import make_session
    from edge.modelfiles import DEFAULT_DIR, load_manifest
    folder = Path((argv if argv is not None else sys.argv[1:])[0] if (argv or sys.argv[1:]) else DEFAULT_DIR)
    files = {p: (f"decoder{s}.onnx", f"autoencoder{s}.onnx") for p, s in (("int8", ".int8"), ("fp32", ""))}
    manifest = load_manifest(folder, need=files["int8"] + files["fp32"] + (REFERENCE,))
    sessions = {p: {m: make_session(folder / f) for m, f in zip(("decoder", "autoencoder"), names, strict=True)}
                for p, names in files.items()}
    r = compare(sessions["int8"], sessions["fp32"], read_reference(folder / REFERENCE),
                float(manifest["plausibility_threshold_m"]), manifest["files"][REFERENCE].get("bounds"))
    print(json.dumps(r.as_dict()))
    return 0 if r.ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
