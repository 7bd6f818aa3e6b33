"""The compiled post-processing core (postproc.c), built on first use with the system C compiler.

At the pipeline's sizes (a few hundred 3x3 products per frame) numpy spends its time in per-call
overhead, not arithmetic; one C call replaces a few hundred numpy calls. The numpy functions stay
the reference: every C function is tested against one (tests/test_native.py), and the pipeline falls
back to them, saying so once, when no compiler is available.

    EDGEPOSE_NATIVE=0     use numpy only
    CC=...                the compiler (default cc)

The library is compiled for the CPU it runs on (-march=native, where the compiler accepts it:
AVX-512 or NEON for the per-sample lanes) and cached per source, flags and CPU in $EDGEPOSE_CACHE or
~/.cache/edgepose, so an edited postproc.c or another CPU sharing the cache rebuilds, and a read-only
install still works.
"""
import ctypes
import hashlib
import os
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from edge import quat

SOURCE = Path(__file__).with_name("postproc.c")
HEADERS = (Path(__file__).with_name("quat.h"),)      # what postproc.c includes: part of the cache key
CFLAGS = ("-O3", "-shared", "-fPIC", "-ffp-contract=off", "-fno-math-errno")
# Tried in order: the first the compiler accepts is used. Either way results are bit-identical
# (no fused multiply-adds, no reassociation); native only makes the lanes wider.
ARCH_FLAGS = (("-march=native",), ())
_lib = None
_error = None


def _cache_dir():
    base = os.environ.get("EDGEPOSE_CACHE") or Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "edgepose"
    return Path(base) / "native"


def _cpu_tag():
    """What identifies this CPU for -march=native: the machine and /proc/cpuinfo's model and feature lines."""
    try:
        info = Path("/proc/cpuinfo").read_text(errors="replace").splitlines()
    except OSError:
        info = []
    keys = ("model name", "flags", "Features", "CPU implementer", "CPU part")
    seen = dict.fromkeys(line for line in info if line.split(":", 1)[0].strip() in keys)
    return os.uname().machine + "\n" + "\n".join(seen)


def shared_constants():
    """The facts postproc.c shares with the Python side, by their names in C: defined once, in edge.physics
    and edge.skeleton, and compiled in as -D flags (exact: repr of a float reads back as the same double)."""
    from edge.physics import ANKLE_HEIGHT, FLOOR_ANKLE, FLOOR_TOE, LOCK_SNAP_M, SUPPORT_FULL_M, SUPPORT_NONE_M
    from edge.ik import ELBOW_CLEARANCE_M, ELBOW_MIN_M, GUARD_GAIN, REACH_START, SHOULDER_PUSH_MAX_M, SHOULDER_REACH_MAX_M
    from edge.skeleton import TOE_HEIGHT
    return {"FLOOR_ANKLE": FLOOR_ANKLE, "FLOOR_TOE": FLOOR_TOE, "TOE_HEIGHT": TOE_HEIGHT, "ANKLE_HEIGHT": ANKLE_HEIGHT,
            "LOCK_SNAP": LOCK_SNAP_M, "SUPPORT_FULL": SUPPORT_FULL_M, "SUPPORT_NONE": SUPPORT_NONE_M,
            "ELBOW_CLEARANCE_M": ELBOW_CLEARANCE_M, "GUARD_GAIN": GUARD_GAIN, "ELBOW_MIN_M": ELBOW_MIN_M,
            "SHOULDER_PUSH_MAX_M": SHOULDER_PUSH_MAX_M, "REACH_START": REACH_START,
            "SHOULDER_REACH_MAX_M": SHOULDER_REACH_MAX_M}


def build(force=False):
    """Compile postproc.c (if not cached) and return the library's path."""
    cc = shlex.split(os.environ.get("CC", "cc"))
    src = SOURCE.read_bytes() + b"".join(h.read_bytes() for h in HEADERS)
    defines = tuple(f"-D{name}={float(value)!r}" for name, value in shared_constants().items())
    tag = hashlib.sha1(src + repr((cc, CFLAGS, ARCH_FLAGS, defines)).encode() + _cpu_tag().encode()).hexdigest()[:12]
    out = _cache_dir() / f"postproc-{tag}.so"
    if out.exists() and not force:
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    try:
        for i, arch in enumerate(ARCH_FLAGS):
            try:
                include = ["-I", str(HEADERS[0].parent)]
                subprocess.run(cc + list(CFLAGS) + list(arch) + list(defines) + include + ["-o", tmp, str(SOURCE), "-lm"],
                               check=True,
                               capture_output=True, text=True, timeout=120)
                break
            except subprocess.CalledProcessError as e:
                if i == len(ARCH_FLAGS) - 1:
                    raise OSError(f"{cc[0]} failed on {SOURCE.name}: {e.stderr.strip()[:400]}") from None
        out.with_suffix(".flags").write_text(" ".join(CFLAGS + arch) + "\n")   # what `python -m edge.native` reports
        os.replace(tmp, out)       # atomic: concurrent builders never load a half-written file
    except FileNotFoundError:
        raise OSError(f"no C compiler ({cc[0]}); install one (apt install gcc) or set CC") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


_P = ctypes.c_void_p
_I = ctypes.c_int
_D = ctypes.c_double


# Mirrors of postproc.c's structs, field for field (addresses of arrays the caller keeps alive, as ints).
def _struct(name, doc, fields):
    return type(name, (ctypes.Structure,), {"__doc__": doc, "_fields_": fields})


Skeleton = _struct("Skeleton", "postproc.c's skeleton: edge.skeleton's tree, the limb chains and poles, ankles, head, neck.",
                   [(k, _I) for k in ("J", "head", "neck")] + [(k, _P) for k in ("parents", "chains", "ankles",
                                                                                   "offsets", "poles")])
PoseRows = _struct("PoseRows", "postproc.c's pose_rows: local, world rotations and positions of R rows.",
                   [(k, _P) for k in ("local", "world", "pos")])
ForwardInputs = _struct("ForwardInputs", "postproc.c's forward_inputs (NumpyFrame.forward's arguments).",
                        [("rot6d", _P), ("rot6d_stride", _I), ("root_m", _P), ("root_stride", _I), ("anchor", _P),
                         ("anchor_stride", _I), ("seg_m", _P), ("seg_flag", _P)])
LimbGoals = _struct("LimbGoals", "postproc.c's limb_goals (NumpyFrame.post's arguments).",
                    [("foot_goals", _P), ("foot_weights", _P), ("foot_ik", _I), ("arm_ik", _I), ("wrists", _P),
                     ("wrists_stride", _I), ("hand_m", _P), ("hand_stride", _I), ("head_m", _P), ("head_stride", _I),
                     ("lift", _P), ("swivel", _D)])
FootLocks = _struct("FootLocks", "postproc.c's foot_locks: edge.ik.FootLock's settings and arrays.",
                    [("release_frames", _D), ("max_slip", _D)] + [(k, _P) for k in ("lock_pos", "since", "weight",
                                                                                       "locked", "raw")]
                    + [("min_gap", _D), ("leg_guard", _D), ("leg_guard_max", _D), ("leg_segs", _P)])
PhysicalParams = _struct("PhysicalParams", "postproc.c's physical_params (edge.criteria.PhysicalPlausibility).",
                         [("segs", _P), ("feet", _P)] + [(k, _D) for k in ("gap", "float_m", "toe_h", "ankle_h",
                                                                           "w_floor", "w_legs", "w_support")])
RefineArgs = _struct("RefineArgs", "postproc.c's refine_args: what ep_refine_step reads besides the core context.",
                     [("rot6d", _P), ("rot6d_stride", _I), ("L", _I), ("eps", _D), ("pos", _P), ("r", _P), ("A", _P),
                      ("g", _P), ("jt", _P), ("max_m", _I), ("n_targets", _I), ("target_joint", _P), ("target_pos", _P),
                      ("target_radius", _P), ("target_w", _P), ("keep_on", _I), ("keep", _P), ("keep_w", _D),
                      ("floor_on", _I), ("floor_w", _D), ("planted_w", _D), ("lock_row", _I),
                      ("prior", _D), ("continuity", _D), ("damping", _D), ("max_step", _D),
                      ("legs_on", _I), ("legs_w", _D), ("legs_clear", _D), ("legs_segs", _P)])
Selection = _struct("Selection", "postproc.c's selection: what ep_frame_costs reads besides the core context.",
                    [("ae_out", _P), ("ae_rot_dim", _I), ("leg_rows", _P), ("legs", _P), ("leg_err", _P),
                     ("physical", _P), ("physical_cost", _P), ("pos", _P), ("ring_cost", _P), ("cost_stride", _I)])


class CoreContext(ctypes.Structure):
    """Mirror of postproc.c's core_context: what the live frame's calls read every frame without being
    told (the skeleton, FootLock's state, the pipeline's buffers and the look-ahead ring)."""
    _fields_ = ([("sk", Skeleton), ("locks", FootLocks)]
                + [(k, _I) for k in ("foot_ik", "arm_ik", "rot6d_stride")]
                + [(k, _P) for k in ("rot6d", "contacts", "goals", "weights")]
                + [("ring_rows", _I)]
                + [(k, _P) for k in ("ring_waist", "ring_anchor", "ring_wrists", "ring_hand", "ring_head", "ring_rot6d",
                                     "ring_contacts", "ring_goal", "ring_weight", "ring_lock_weight", "out_local",
                                     "out_world", "out_pos", "ae_in", "ae_local", "ae_root_local", "frame_in",
                                     "frame_offsets", "prev")]
                + [("fps", _D), ("ring_features", _P), ("dec_features", _P), ("dec_rows", _I), ("ring_hidden", _P),
                   ("hidden", _I), ("out_contacts", _P), ("n_features", _I), ("imus", _I), ("floor_lift", _P),
                   ("ring_seg_m", _P), ("ring_seg_flag", _P), ("imu_joints", _P), ("segments", _I),
                   ("good_in", _P), ("frame_len", _I), ("position_limit", _D), ("dec_latent", _P), ("latents", _P),
                   ("latent_dim", _I), ("target_row", _I), ("target_joint", _P), ("target_goal", _P),
                   ("target_weight", _P), ("swivel", _D), ("smooth_prev", _P), ("smooth_speed", _P), ("smooth_before", _P),
                   ("smooth_before_speed", _P),
                   ("smooth_keep", _P), ("smooth_min_cut", _D), ("smooth_beta", _D), ("smooth_speed_weight", _D),
                   ("keep_shown", _I), ("shown_slot", _I), ("shown_row", _I)])


_SIGNATURES = {
    "ep_forward": [ctypes.POINTER(Skeleton), _I, ctypes.POINTER(ForwardInputs), ctypes.POINTER(PoseRows)],
    "ep_local_pose": [_I, _I, _P, _P, _I, _P, _P, _P],
    "ep_leg_error": [_I, _I, _P, _I, _P, _P, _P, _P, _P, _P],
    "ep_foot_locks": [ctypes.POINTER(Skeleton), _I, _P, _P, _P, ctypes.POINTER(FootLocks), _P],
    "ep_frame_features": [_P, _P, _P, _D, _P, _P, _P],
    "ep_imu_features": [_I, _P, _P, _P, _P],
    "ep_orientation_features": [_P, _P],
    "ep_physical_cost": [_I, _I, _P, _P, _P, ctypes.POINTER(PhysicalParams), _P],
    "ep_post": [ctypes.POINTER(Skeleton), _I, ctypes.POINTER(LimbGoals), ctypes.POINTER(PoseRows)],
    "ep_on_user": [ctypes.POINTER(Skeleton), _P, _P, ctypes.POINTER(PoseRows)],
    "ep_switch_to": [_I, _P, _I, _D],
    "ep_frame_poses": [ctypes.POINTER(CoreContext), _I, _I, _I, _I, _I, _D, _P, _P, _P, _P, _I],
    "ep_frame_costs": [ctypes.POINTER(CoreContext), ctypes.POINTER(Selection), _I, _I, _D, _D, _I, _D],
    "ep_refine_step": [ctypes.POINTER(CoreContext), ctypes.POINTER(RefineArgs), _I, _P, _P, _P],
    "ep_refine_fill": [_I, _P, _P, _P],
    "ep_from_matrix": [_I, _P, _P],
    "ep_emit": [ctypes.POINTER(CoreContext), _I, _I],
    "ep_smooth_rows": [ctypes.POINTER(CoreContext), _P, _I, _I, _I],
    "ep_frame_inputs": [ctypes.POINTER(CoreContext), _I, _I, _I, _I, _I, _D, _P],
    "ep_encode_pose": [_I, _I, _I, ctypes.c_uint, _P, _P, _I, _P, _I, _I, _I, _P, _I],
    "ep_max_joints": [],
    "ep_layout": [_P, _I],
}
_RETURNS_INT = {"ep_switch_to", "ep_max_joints", "ep_encode_pose", "ep_layout", "ep_frame_poses",
                "ep_frame_costs", "ep_frame_inputs"}
_RETURNS_DOUBLE = {"ep_refine_step"}
_MIRRORS = (Skeleton, PoseRows, ForwardInputs, LimbGoals, FootLocks, PhysicalParams, Selection, RefineArgs)


def layout_mismatch(lib):
    """What differs between postproc.c's structs and their ctypes mirrors ('' when nothing does): the
    sizes of each struct and the offset of every core_context field, as the compiler laid them out."""
    c = np.zeros(128, np.int64)
    n = lib.ep_layout(c.ctypes.data, len(c))
    py = [ctypes.sizeof(m) for m in _MIRRORS] + [ctypes.sizeof(CoreContext)]
    py += [getattr(CoreContext, name).offset for name, _ in CoreContext._fields_]
    names = [m.__name__ for m in _MIRRORS] + ["CoreContext"] + [f"CoreContext.{f}" for f, _ in CoreContext._fields_]
    if n != len(py):
        head = len(_MIRRORS) + 1
        return f"postproc.c lays out {n - head} core_context fields, the ctypes mirror has {len(py) - head}"
    bad = [f"{w} (C {int(a)}, ctypes {b})" for w, a, b in zip(names, c[:n], py, strict=True) if int(a) != b]
    return "; ".join(bad)


def load():
    """The ctypes library, or None (with the reason in `why_unavailable()`) when it cannot be had."""
    global _lib, _error
    if _lib is not None or _error is not None:
        return _lib
    if os.environ.get("EDGEPOSE_NATIVE", "1") == "0":
        _error = "disabled by EDGEPOSE_NATIVE=0"
        return None
    try:
        lib = ctypes.CDLL(str(build()))
    except OSError as e:
        _error = str(e)
        print(f"edgepose: compiled post-processing unavailable ({_error}); using numpy (slower)", file=sys.stderr)
        return None
    for name, args in _SIGNATURES.items():
        fn = getattr(lib, name)
        fn.argtypes, fn.restype = args, (_I if name in _RETURNS_INT else _D if name in _RETURNS_DOUBLE else None)
    from edge.skeleton import NUM_JOINTS
    mismatch = layout_mismatch(lib)
    if mismatch:        # a struct edited on one side only: calling in would corrupt memory
        _error = f"postproc.c's structs and their ctypes mirrors in edge/native/__init__.py differ: {mismatch}"
        print(f"edgepose: compiled post-processing unavailable ({_error}); using numpy (slower)", file=sys.stderr)
        return None
    if lib.ep_max_joints() < NUM_JOINTS:
        _error = f"postproc.c is built for at most {lib.ep_max_joints()} joints; the skeleton has {NUM_JOINTS}"
        print(f"edgepose: compiled post-processing unavailable ({_error}); using numpy (slower)", file=sys.stderr)
        return None
    _lib = lib
    return _lib


def build_flags():
    """The compiler flags the cached library was built with ('' when unknown)."""
    try:
        return build().with_suffix(".flags").read_text().strip()
    except OSError:
        return ""


def why_unavailable():
    load()
    return _error


def from_matrix(m, out=None):
    """edge.quat.from_matrix of rotations m [...,3,3]: in the compiled core when it loads (ep_from_matrix,
    the same bits; about 1 us for a pose against numpy's ~100), else numpy. Into `out` [...,4] when given
    (float64, C-contiguous: a per-frame caller reuses one), else a new array."""
    lib = load()
    if (lib is None or not isinstance(m, np.ndarray) or m.dtype != np.float64 or not m.flags.c_contiguous
            or m.shape[-2:] != (3, 3)):
        q = quat.from_matrix(m)
        if out is None:
            return q
        out[...] = q
        return out
    out = np.empty(m.shape[:-2] + (4,)) if out is None else out
    lib.ep_from_matrix(m.size // 9, addr(m), checked_addr(out, np.float64, m.shape[:-2] + (4,), "quaternions out"))
    return out


def from_matrix_bound(m, out):
    """A call of no arguments doing from_matrix(m, out) on these two arrays for good: their addresses
    taken once, so a per-frame caller (the service's pose stream) pays one ctypes call (~0.6 us against
    from_matrix's ~4 of checks)."""
    lib = load()
    if lib is None:
        return lambda: from_matrix(m, out)
    n = m.size // 9
    src = checked_addr(m, np.float64, m.shape, "rotations")
    dst = checked_addr(out, np.float64, m.shape[:-2] + (4,), "quaternions out")
    return lambda: lib.ep_from_matrix(n, src, dst)


def addr(a):
    """Address of an array's first element (the caller guarantees dtype and layout; `checked_addr`
    checks them). Not __array_interface__: on numpy 2 that grows a cache on every call on a view (a
    per-frame leak)."""
    return a.ctypes.data


def checked_addr(a, dtype, shape=None, what="array"):
    """addr(a) after checking what C will assume of it: its dtype, C-contiguity and (when given) its
    shape, with None for any length. Raises TypeError or ValueError saying which."""
    if not isinstance(a, np.ndarray) or a.dtype != np.dtype(dtype):
        got = a.dtype if isinstance(a, np.ndarray) else type(a).__name__
        raise TypeError(f"{what}: the compiled core needs {np.dtype(dtype).name}, got {got}")
    if not a.flags.c_contiguous:
        raise ValueError(f"{what}: the compiled core needs a C-contiguous array (np.ascontiguousarray), got a view")
    if shape is not None and (a.ndim != len(shape) or any(w is not None and w != g for w, g in zip(shape, a.shape, strict=True))):
        raise ValueError(f"{what}: the compiled core needs shape {shape}, got {a.shape}")
    return a.ctypes.data


def rows(a, row_ndim, dtype=np.float64):
    """(address, row stride in elements) of `a`, one row of `row_ndim` trailing dims or a stack of them.

    A single row gets stride 0 (every row shares it). Rows must be contiguous inside; the stack may be strided."""
    if a.dtype != dtype:
        raise TypeError(f"expected {np.dtype(dtype).name}, got {a.dtype}")
    inner = a.shape[a.ndim - row_ndim:]
    if a.ndim == row_ndim:
        if not a.flags.c_contiguous:
            raise ValueError("a shared row must be contiguous")
        return addr(a), 0
    want = a.itemsize
    for n, s in zip(reversed(inner), reversed(a.strides[a.ndim - row_ndim:]), strict=True):
        if s != want:
            raise ValueError("rows must be contiguous inside")
        want *= n
    return addr(a), a.strides[0] // a.itemsize
