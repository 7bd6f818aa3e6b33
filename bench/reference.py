"""PyTorch eager reference of the decoder step, run per frame the way research code runs it.

TorchDecoder has the interface edge.inference.Decoder offers the pipeline (the same buffers, `state`,
the ping-pong and the one-shot mode), but each step() wraps the buffers with torch.from_numpy, calls
models.nets.DecoderStep (built from models/checkpoints as models/export.py builds it for ONNX) under
torch.no_grad() on one thread, and copies the outputs back with .numpy(). bench/pipeline.py --compare
times it against the ONNX Runtime decoder, alone and inside the whole pipeline.
"""
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from edge.inference import Decoder
from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from models.export import load_checkpoint
from models.nets import DecoderStep


def load_step(ckpt=ROOT / "models" / "checkpoints"):
    """The trained decoder step in eval mode, with torch on one thread."""
    torch.set_num_threads(1)
    cvae, _, _ = load_checkpoint(ckpt)
    return DecoderStep(cvae).eval()


class TorchDecoder(Decoder):
    """edge.inference.Decoder (same buffers, `state`, ping-pong, one-shot mode) whose step runs
    `model` in PyTorch eager mode instead of an ONNX Runtime session."""

    def __init__(self, model, rows, latent_dim, hidden_dim, n_features, recurrent=True):
        self.model, self.rows, self.capacity, self.recurrent = model, rows, rows, recurrent
        self.features = np.zeros((rows, n_features), np.float32)
        self.latent = np.zeros((rows, latent_dim), np.float32)
        self.hidden = [np.zeros((rows, hidden_dim), np.float32), np.zeros((rows, hidden_dim), np.float32)]
        self.rot6d = np.zeros((rows, model.rot_head.out_features), np.float32)
        self.contacts = np.zeros((rows, 2), np.float32)
        self._cur = 0

    def resize(self, rows):
        raise NotImplementedError("the reference runs a fixed N")

    def step(self):
        with torch.no_grad():
            rot6d, contacts, hidden = self.model(torch.from_numpy(self.features), torch.from_numpy(self.latent),
                                                 torch.from_numpy(self.state))
        self.rot6d[:] = rot6d.numpy()
        self.contacts[:] = contacts.numpy()
        self.hidden[1 - self._cur][:] = hidden.numpy()
        if self.recurrent:
            self._cur = 1 - self._cur


def reference_pipeline(model, samples):
    """A fp32 Pipeline whose decoder and transition recompute are TorchDecoders on `model`."""
    pipe = Pipeline(PipelineOptions(samples=samples, precision="fp32"))
    m = pipe.manifest
    dims = m["latent"], m["hidden"], m["features"]
    pipe.decoder = TorchDecoder(model, pipe.rows, *dims)
    pipe.recompute = TorchDecoder(model, pipe.lookahead + 1, *dims, recurrent=False)
    pipe.decoder.latent[:samples] = pipe.latents
    pipe.reset()
    return pipe


def max_abs_diff(session, model, manifest, rows=8, steps=5, seed=0):
    """Largest |ONNX - PyTorch| in rot6d, contacts and both GRU state buffers, for an ONNX Decoder on
    `session` and a TorchDecoder fed the same inputs: `steps` recurrent frames, then a one-shot call."""
    rng = np.random.default_rng(seed)
    dims = manifest["latent"], manifest["hidden"], manifest["features"]
    mean, std = model.norm.mean.numpy(), model.norm.std.numpy()
    worst = 0.0
    for recurrent, n in ((True, steps), (False, 1)):
        onnx = Decoder(session, rows, *dims, recurrent=recurrent)
        ref = TorchDecoder(model, rows, *dims, recurrent=recurrent)
        latent = rng.standard_normal(onnx.latent.shape).astype(np.float32)
        hidden = np.tanh(rng.standard_normal(onnx.state.shape)).astype(np.float32)
        for d in (onnx, ref):
            d.latent[:] = latent
            d.state[:] = hidden
        for _ in range(n):
            features = (mean + std * rng.standard_normal(onnx.features.shape)).astype(np.float32)
            for d in (onnx, ref):
                d.features[:] = features
                d.step()
            for a, b in zip((onnx.rot6d, onnx.contacts, *onnx.hidden), (ref.rot6d, ref.contacts, *ref.hidden), strict=True):
                worst = max(worst, float(np.abs(a - b).max()))
    return worst
