"""ONNX Runtime sessions for the decoder step and the pose autoencoder, tuned for one low-power core.

Buffers are allocated once and bound with IOBinding, so a frame's inference allocates nothing.
"""
import functools

import numpy as np

from edge.modelfiles import ModelError


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
    fn(name, "cpu", 0, arr.dtype, list(arr.shape), arr.ctypes.data)


def bound_run(session, io):
    """A call that runs `session` on IOBinding `io`: session.run_with_iobinding(io), with two per-call
    costs of a small CPU graph taken out (on an Intel Xeon, of a 7 us autoencoder call):
    - one RunOptions made here, where a call given none has the binding make a default one (about 1 us);
    - made straight on ONNX Runtime's C++ binding where it has one: the Python wrapper around it checks
      WebGPU graph capture on every call (onnxruntime 1.2x, about 0.5 us). Where the wrapper's internals
      are not there (another onnxruntime), the public call."""
    import onnxruntime as ort
    options = ort.RunOptions()
    raw, raw_io = getattr(session, "_sess", None), getattr(io, "_iobinding", None)
    if raw is not None and raw_io is not None and callable(getattr(raw, "run_with_iobinding", None)):
        return functools.partial(raw.run_with_iobinding, raw_io, options)
    return functools.partial(session.run_with_iobinding, io, options)


class Decoder:
    """The CVAE decoder step on `rows` rows at once, on preallocated buffers.

    recurrent=True keeps the GRU state here, ping-ponged between two buffers so input and output never
    alias (`state` is what the next step reads). recurrent=False is a one-shot batch: fill `hidden`.
    Buffers hold `rows` rows for good; `resize` runs the first k of them (adaptive N) by rebinding
    views, so rows keep their contents and nothing is reallocated.
    """

    def __init__(self, session, rows, latent_dim, hidden_dim, n_features, recurrent=True, shared_features=False):
        inputs = {i.name: i for i in session.get_inputs()}
        if set(inputs) != {"features", "latent", "hidden"}:
            raise ModelError(f"decoder model: expected inputs features/latent/hidden, found {sorted(inputs)}")
        self.session, self.capacity = session, rows
        # shared_features: every row reads row 0's features (one frame's N samples). A graph whose features
        # have rows of their own (v0.5's export names them M, the others N) takes that one row and
        # broadcasts it, so the first layer's feature part runs once a frame; older graphs read them all.
        self.shared_features = shared_features and inputs["features"].shape[0] != inputs["latent"].shape[0]
        self.features = np.zeros((rows, n_features), np.float32)
        self.latent = np.zeros((rows, latent_dim), np.float32)
        self.hidden = [np.zeros((rows, hidden_dim), np.float32), np.zeros((rows, hidden_dim), np.float32)]
        out_dims = {o.name: o.shape[1] for o in session.get_outputs()}
        self.rot6d = np.zeros((rows, out_dims["rot6d"]), np.float32)
        self.contacts = np.zeros((rows, 2), np.float32)
        self._cur = 0
        self.recurrent = recurrent
        self.resize(rows)

    def resize(self, rows):
        """Run the first `rows` rows from now on (1 <= rows <= capacity)."""
        if not 1 <= rows <= self.capacity:
            raise ValueError(f"decoder rows must be 1..{self.capacity}, got {rows}")
        self.rows = rows
        self._io = []
        for k in range(2 if self.recurrent else 1):
            io = self.session.io_binding()
            _bind(io, "features", self.features[:1 if self.shared_features else rows])
            _bind(io, "latent", self.latent[:rows])
            _bind(io, "hidden", self.hidden[k][:rows])
            _bind(io, "rot6d", self.rot6d[:rows], output=True)
            _bind(io, "contacts", self.contacts[:rows], output=True)
            _bind(io, "hidden_out", self.hidden[1 - k][:rows], output=True)
            self._io.append(io)
        self._run = [bound_run(self.session, io) for io in self._io]

    @property
    def state(self):
        """The GRU state the next step reads (after a step: the state it wrote)."""
        return self.hidden[self._cur]

    @property
    def current(self):
        """Which of `hidden` the next step reads (after a recurrent step: the one it wrote)."""
        return self._cur

    @property
    def last_read(self):
        """Which of `hidden` the last recurrent step read (its input; the step wrote the other)."""
        return 1 - self._cur

    def reset(self):
        self.hidden[0][:] = 0
        self.hidden[1][:] = 0
        self._cur = 0

    def step(self):
        """Run one frame on the bound buffers (fill `features`, `latent` and, one-shot, `state` first)."""
        self._run[self._cur]()
        if self.recurrent:
            self._cur = 1 - self._cur


class JacobianBatch:
    """The refiner's batch on the Jacobian graph (models.nets.JacobianStep): `rows` latents decoded from
    one frame's features [1,F] and GRU state (hidden[0], [1,H]) into rot6d [rows,D], on bound buffers.
    Fill features, hidden[0] and latent as for a one-shot Decoder, then step()."""

    def __init__(self, session, rows, latent_dim, hidden_dim, n_features):
        names = {i.name for i in session.get_inputs()}
        if names != {"features", "latent", "hidden"} or [o.name for o in session.get_outputs()] != ["rot6d"]:
            raise ModelError("Jacobian model: expected inputs features/latent/hidden and output rot6d; "
                             "re-export it (python -m models.export --jacobian-only)")
        self.session, self.rows = session, rows
        self.features = np.zeros((1, n_features), np.float32)
        self.latent = np.zeros((rows, latent_dim), np.float32)
        self.hidden = [np.zeros((1, hidden_dim), np.float32)]
        self.rot6d = np.zeros((rows, session.get_outputs()[0].shape[1]), np.float32)
        self._io = session.io_binding()
        _bind(self._io, "features", self.features)
        _bind(self._io, "latent", self.latent)
        _bind(self._io, "hidden", self.hidden[0])
        _bind(self._io, "rot6d", self.rot6d, output=True)
        self._run = bound_run(session, self._io)

    def step(self):
        self._run()


class Autoencoder:
    """The plausibility autoencoder: local positions [B,J*3] -> rotations [B,(J-1)*6].

    Calls with the batch size given at construction (or by `resize`) go through preallocated, bound buffers.
    """

    def __init__(self, session, rows=None):
        self.session = session
        self.rows = self.capacity = rows
        if rows:
            self.inp = np.zeros((rows, session.get_inputs()[0].shape[1]), np.float32)
            self.out = np.zeros((rows, session.get_outputs()[0].shape[1]), np.float32)
            self.resize(rows)

    def resize(self, rows):
        """Bind the first `rows` rows of the buffers (adaptive N)."""
        if not self.capacity or not 1 <= rows <= self.capacity:
            raise ValueError(f"autoencoder rows must be 1..{self.capacity}, got {rows}")
        self.rows = rows
        self._io = self.session.io_binding()
        _bind(self._io, "positions", self.inp[:rows])
        _bind(self._io, "rot6d", self.out[:rows], output=True)
        self._run = bound_run(self.session, self._io)

    def __call__(self, positions):
        if self.rows and len(positions) == self.rows:
            self.inp[:self.rows] = positions
            return self.run()
        return self.session.run(None, {"positions": np.ascontiguousarray(positions, dtype=np.float32)})[0]

    def run(self):
        """Run on the bound rows of `inp` as they are (a caller that filled them itself); returns `out`'s rows."""
        self._run()
        return self.out[:self.rows]


# int8 met fp32's accuracy on val (python -m quantize.report) and runs the frame >= 1.5x faster at N=100.
DEFAULT_PRECISION = "int8"


def model_files(precision, manifest):
    """(decoder file, autoencoder file) a precision runs: the manifest's `precisions` entry when it has
    one (python -m quantize keeps the fp32 autoencoder for int8 where int8 measured slower), else
    <model>.<precision>.onnx."""
    chosen = manifest.get("precisions", {}).get(precision, {})
    suffix = "" if precision == "fp32" else f".{precision}"
    return tuple(chosen.get(m, f"{m}{suffix}.onnx") for m in ("decoder", "autoencoder"))
