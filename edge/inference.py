"""ONNX Runtime sessions for the decoder step and the pose autoencoder, tuned for one low-power core.

Buffers are allocated once and bound with IOBinding, so a frame's inference allocates nothing.
"""
import numpy as np

from edge.modelfiles import ModelError, load_manifest


def make_session(path, threads=1):
    import onnxruntime as ort
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.log_severity_level = 3
    try:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types for bad files
        raise ModelError(f"cannot load model {path}: {e}") from None


def _bind(io, name, arr, output=False):
    fn = io.bind_output if output else io.bind_input
    if output:
        fn(name, "cpu", 0, arr.dtype, list(arr.shape), arr.ctypes.data)
    else:
        fn(name, "cpu", 0, arr.dtype, list(arr.shape), arr.ctypes.data)


class Decoder:
    """The CVAE decoder for N samples at once: features [24] broadcast to N rows, fixed latents, GRU state kept here."""

    def __init__(self, path, samples, latent_dim, hidden_dim, n_features, threads=1):
        self.session = make_session(path, threads)
        names = {i.name for i in self.session.get_inputs()}
        if names != {"features", "latent", "hidden"}:
            raise ModelError(f"{path}: expected inputs features/latent/hidden, found {sorted(names)}")
        n = samples
        self.features = np.zeros((n, n_features), np.float32)
        self.latent = np.zeros((n, latent_dim), np.float32)
        self.hidden = [np.zeros((n, hidden_dim), np.float32), np.zeros((n, hidden_dim), np.float32)]
        out_dims = {o.name: o.shape[1] for o in self.session.get_outputs()}
        self.rot6d = np.zeros((n, out_dims["rot6d"]), np.float32)
        self.contacts = np.zeros((n, 2), np.float32)
        # Two bindings that ping-pong the hidden state, so input and output never alias.
        self._io = []
        for k in range(2):
            io = self.session.io_binding()
            _bind(io, "features", self.features)
            _bind(io, "latent", self.latent)
            _bind(io, "hidden", self.hidden[k])
            _bind(io, "rot6d", self.rot6d, output=True)
            _bind(io, "contacts", self.contacts, output=True)
            _bind(io, "hidden_out", self.hidden[1 - k], output=True)
            self._io.append(io)
        self._cur = 0

    @property
    def state(self):
        """The GRU state the next step reads (after a step: the state it wrote)."""
        return self.hidden[self._cur]

    def reset(self):
        self.hidden[0][:] = 0
        self.hidden[1][:] = 0
        self._cur = 0

    def step(self):
        """Run one frame on the bound buffers (fill `features`/`latent` first)."""
        self.session.run_with_iobinding(self._io[self._cur])
        self._cur = 1 - self._cur


class Autoencoder:
    """The plausibility autoencoder: local positions [B,J*3] -> rotations [B,(J-1)*6]."""

    def __init__(self, path, threads=1):
        self.session = make_session(path, threads)

    def __call__(self, positions):
        return self.session.run(None, {"positions": np.ascontiguousarray(positions, dtype=np.float32)})[0]


def load_models(folder=None, samples=1, threads=1, precision="fp32"):
    kw = {} if folder is None else {"folder": folder}
    suffix = "" if precision == "fp32" else f".{precision}"
    names = (f"decoder{suffix}.onnx", f"autoencoder{suffix}.onnx")
    manifest = load_manifest(need=names, **kw)
    dec = Decoder(manifest["paths"][names[0]], samples, manifest["latent"], manifest["hidden"], manifest["features"], threads)
    ae = Autoencoder(manifest["paths"][names[1]], threads)
    return manifest, dec, ae
