"""Shared by the int8 build and its report: model names, closed-loop decoder rollouts, FK, timing, data.

numpy + onnxruntime only (the mocap windows come from motion.dataset, which needs no torch).
"""

import numpy as np

from edge.int8check import head_anchored_positions  # noqa: F401  (re-exported: quantize.build, tests)
from edge.inference import Autoencoder, Decoder, JacobianBatch, make_session
from edge.skeleton import NUM_PREDICTED
from motion.timing import time_calls

MODELS = ("decoder", "autoencoder")


def fp32_name(model):
    return f"{model}.onnx"


def int8_name(model):
    return f"{model}.int8.onnx"


def hidden_width(session):
    """The GRU width a decoder-like graph was exported with (its `hidden` input's second axis)."""
    width = {i.name: i.shape for i in session.get_inputs()}["hidden"][1]
    if not isinstance(width, int):
        raise ValueError(f"the decoder graph's hidden input has no fixed width ({width!r}): re-export it")
    return width


def rollout(session, features, latent, hidden=None):
    """Closed-loop decoder rollout: features [T,B,F] (one stream per row), latent [B,Z].

    Each step feeds the GRU state the model itself wrote (as the runtime does). Returns rot6d
    [T,B,120], contacts [T,B,2] and the hidden state fed at each step [T,B,H] (the calibration input).
    """
    T, B, _ = features.shape
    H = hidden_width(session)
    h = np.zeros((B, H), np.float32) if hidden is None else hidden.astype(np.float32)
    latent = np.ascontiguousarray(latent, np.float32)
    rot6d = np.zeros((T, B, 6 * NUM_PREDICTED), np.float32)
    contacts = np.zeros((T, B, 2), np.float32)
    hidden_in = np.zeros((T, B, H), np.float32)
    for t in range(T):
        hidden_in[t] = h
        r, c, h = session.run(None, {"features": np.ascontiguousarray(features[t], np.float32), "latent": latent,
                                     "hidden": h})
        rot6d[t], contacts[t] = r, c
    return rot6d, contacts, hidden_in


def _call_us(call, frames, warmup):
    """Median and p99 (microseconds) of `call()`, after `warmup` calls, on whatever CPU the caller is pinned to."""
    for _ in range(warmup):
        call()
    us = time_calls(lambda i: call(), frames)
    return {"p50": float(np.median(us)), "p99": float(np.percentile(us, 99))}


def _decode_call_us(kind, path, rows, frames, warmup):
    """One bare step of a decoder-like runtime class (`kind`: Decoder or JacobianBatch) on `rows` rows of
    random features and latents, through its IOBinding path."""
    session = make_session(path)
    batch = kind(session, rows, 30, hidden_width(session), session.get_inputs()[0].shape[1])
    rng = np.random.default_rng(0)
    batch.features[:] = rng.standard_normal(batch.features.shape) * 0.3
    batch.latent[:] = rng.standard_normal(batch.latent.shape)
    return _call_us(batch.step, frames, warmup)


def decoder_call_us(path, rows, frames=400, warmup=50):
    """One bare decoder step on `rows` rows (edge.inference.Decoder)."""
    return _decode_call_us(Decoder, path, rows, frames, warmup)


def jacobian_call_us(path, rows, frames=400, warmup=50):
    """One bare call of the refiner's batch graph on `rows` latents (edge.inference.JacobianBatch)."""
    return _decode_call_us(JacobianBatch, path, rows, frames, warmup)


def autoencoder_call_us(path, rows, frames=400, warmup=50):
    """One bare autoencoder call on `rows` rows (edge.inference.Autoencoder)."""
    ae = Autoencoder(make_session(path), rows)
    ae.inp[:] = np.random.default_rng(0).standard_normal(ae.inp.shape) * 0.3
    return _call_us(ae.run, frames, warmup)


def pin_one_core():
    """Pin this process to one core (the board's budget); returns the core or None where not possible."""
    import os
    try:
        core = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {core})
        return core
    except (AttributeError, OSError):
        return None


def mocap_windows(data, split, windows, window, seed, noise=True, n_features=None):
    """`windows` random training-style windows of one split: the decoder's features [W,B,F] (time-major;
    with random extra IMUs as training has them, unless n_features is 24, a model without IMU inputs),
    the head-anchored ground truth [W,B,J,3], the puck rotation in the character frame [W,B,3,3] and the
    ground-truth local poses for the autoencoder. Uses motion.dataset (cached in .cache/)."""
    from motion.synth import DeviceNoise
    from motion.dataset import build, make_batch, pose_batch, window_starts
    cs = build(data, split)
    rng = np.random.default_rng(seed)
    starts = window_starts(cs, window)
    pick = np.sort(rng.choice(starts, size=min(windows, len(starts)), replace=False))
    from edge.features import NUM_FEATURES, NUM_POINT_FEATURES
    from edge.imus import ImuNoise
    imus = n_features is None or n_features > NUM_POINT_FEATURES
    b = make_batch(cs, pick, window, rng, DeviceNoise() if noise else None, ImuNoise() if noise else None, with_imus=imus,
                   orientations=n_features is not None and n_features > NUM_FEATURES)
    if not imus:
        b["features"] = b["features"][..., :NUM_POINT_FEATURES]
    elif "orient" in b:             # the upper-body head's orientations
        b["features"] = np.concatenate([b["features"], b["orient"]], axis=-1)
    frames = rng.choice(len(cs.root), size=min(4096, len(cs.root)), replace=False)
    poses = pose_batch(cs, frames)
    return {"features": b["features"], "gt_rel": b["gt_rel"], "root_rot": b["root_rot"], "poses": poses}


def latents_for(rows, latent_dim=30, seed=0):
    """Row 0 at the prior mean (what N=1 runs), the rest drawn like SSI's N samples."""
    z = np.random.default_rng(seed).standard_normal((rows, latent_dim)).astype(np.float32)
    z[0] = 0.0
    return z
