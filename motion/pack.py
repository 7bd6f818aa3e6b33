"""The training pack: the whole retargeted train and val set in one file that travels (to an accelerator).

    python -m motion.pack [--data ../shared/mocap] [--out .cache/pack/edgepose-pack.npz] [--sources ...]

`models.train --data PACK` (and motion.dataset.build) read it instead of the mocap folder. What it holds
is what training reads, motion.dataset's ClipSet per split, in this form:
- rotations: each joint's local quaternion in Q13 integers (1/8192; the error is measured at build time
  as FK joint positions, in mm, and printed and recorded); 30 fps clips keep only their own frames (the
  60 Hz frames between them are slerps of their neighbours, motion.retarget.resample, and are made
  again on load); second differences in time per clip, channel by channel, LZMA-compressed.
- root: positions in 0.1 mm integers, likewise; contacts: one bit per foot and frame (60 Hz).
- the clip names, the manifest's sha256 and the pack's own sha256 beside it in PACK.json.
It holds derived training data, not the clips' files; like the clips it is never committed (.cache/).
"""
import argparse
import hashlib
import json
import lzma
import os
from pathlib import Path

import numpy as np

from edge.progress import Progress

ROT_SCALE = 8192.0          # Q13 quaternion components
ROOT_SCALE = 10000.0        # 0.1 mm
DEFAULT_PACK = Path(".cache/pack/edgepose-pack.npz")
FORMAT = "edgepose-pack/1"


class PackError(ValueError):
    """A pack file that is not one, or that does not hold what was asked for."""


def is_pack(path):
    return Path(path).is_file() and str(path).endswith(".npz")


def _second_difference(x):
    """[F,C] integers -> [F,C] second differences (x[-1] = x[-2] = 0 before the clip)."""
    return np.diff(x, n=2, axis=0, prepend=np.zeros((2,) + x.shape[1:], x.dtype))


def _undo_second_difference(d):
    return np.cumsum(np.cumsum(d, axis=0, dtype=np.int64), axis=0)


def _compress(parts, dtype):
    """Per-clip [F_i, C] integer arrays -> LZMA bytes of their second differences, channel-major."""
    d = np.concatenate([_second_difference(p.astype(np.int64)) for p in parts])
    info = np.iinfo(dtype)
    if d.min() < info.min or d.max() > info.max:
        raise PackError(f"a second difference ({d.min()}..{d.max()}) does not fit {np.dtype(dtype).name}: "
                        "a clip jumps between frames (a quaternion sign flip that quat.unroll missed?)")
    return np.frombuffer(lzma.compress(np.ascontiguousarray(d.astype(dtype).T).tobytes(), preset=6), np.uint8)


def _decompress(blob, dtype, channels, lengths):
    d = np.frombuffer(lzma.decompress(blob.tobytes()), dtype).reshape(channels, -1).T
    out, at = [], 0
    for n in lengths:
        out.append(_undo_second_difference(d[at:at + n]))
        at += n
    return out


def _native_step(relative_names, rows):
    """2 for clips recorded at 30 fps (their 60 Hz frames alternate recorded / interpolated), else 1."""
    fps = {r["file"]: float(r["fps"]) for r in rows}
    return np.array([2 if fps[n] < 45 else 1 for n in relative_names], np.int8)


def _stored_frames(n, step):
    """Which of a clip's n frames (60 Hz) the pack keeps: all, or (step 2, a 30 fps clip) every other
    one and the last, so that each frame left out lies between two kept ones."""
    return np.arange(n) if step == 1 else np.unique(np.append(np.arange(0, n, 2), n - 1))


def _expand(q_kept, root_kept, step, n):
    """A clip's kept frames back to its n frames at 60 Hz: a frame left out is the slerp (lerp for the
    root) halfway between its neighbours, as motion.retarget.resample made it from the 30 fps file.
    (The files say 0.0333333 s a frame, so the resampler's halfway is 0.5 +- 1e-4: pack_error_mm
    measures what that and the rounding cost.)"""
    if step == 1:
        return q_kept, root_kept
    from edge import quat
    kept = _stored_frames(n, step)
    rot = np.empty((n,) + q_kept.shape[1:])
    root = np.empty((n, 3))
    rot[kept], root[kept] = q_kept, root_kept
    gap = np.setdiff1d(np.arange(n), kept)
    rot[gap] = quat.slerp(rot[gap - 1], rot[gap + 1], np.full(rot[gap].shape[:-1], 0.5))
    root[gap] = 0.5 * (root[gap - 1] + root[gap + 1])
    return rot, root


def _split_arrays(cs, steps):
    spans = [(s + _stored_frames(n, k)) for s, n, k in zip(cs.starts, cs.lengths(), steps, strict=True)]
    return [cs.rotations[i] for i in spans], [cs.root[i] for i in spans]


def build_pack(data, out=DEFAULT_PACK, sources=None):
    """Read (or reuse the cache of) the retargeted train and val sets and write the pack. Returns its info."""
    from motion import dataset as ds
    out = Path(out)
    rows = ds.read_manifest(data)
    if rows is None:
        raise PackError(f"{data}: no MANIFEST.tsv (the pack needs the splits)")
    arrays, info = {}, {"format": FORMAT, "sources": sources or sorted(ds.SOURCE_FOLDERS),
                        "manifest_sha256": hashlib.sha256((Path(data) / "MANIFEST.tsv").read_bytes()).hexdigest(),
                        "rot_scale": ROT_SCALE, "root_scale": ROOT_SCALE, "splits": {}}
    for split in ("train", "val"):
        cs = ds.build(data, split, sources)
        names = [os.path.relpath(n, data) for n in cs.names]
        steps = _native_step(names, rows)
        rots, roots = _split_arrays(cs, steps)
        J = cs.rotations.shape[1]
        q_int = [np.round(r.reshape(len(r), -1) * ROT_SCALE) for r in rots]
        p_int = [np.round(r * ROOT_SCALE) for r in roots]
        arrays[f"{split}_rot"] = _compress(q_int, np.int16)
        arrays[f"{split}_root"] = _compress(p_int, np.int32)
        arrays[f"{split}_contacts"] = np.packbits(cs.contacts.astype(bool), axis=None)
        arrays[f"{split}_lengths"] = cs.lengths().astype(np.int64)
        arrays[f"{split}_stored"] = np.array([len(r) for r in rots], np.int64)
        arrays[f"{split}_steps"] = steps
        arrays[f"{split}_names"] = np.array(names)
        info["splits"][split] = {"clips": len(cs.names), "frames_60hz": int(len(cs.root)),
                                 "stored_frames": int(sum(len(r) for r in rots)), "joints": int(J),
                                 "minutes": len(cs.root) / 3600}
    out.parent.mkdir(parents=True, exist_ok=True)
    arrays["info"] = np.array(json.dumps(info))
    np.savez(out, **arrays)
    info["bytes"] = out.stat().st_size
    info["sha256"] = hashlib.sha256(out.read_bytes()).hexdigest()
    info["error_mm"] = pack_error_mm(out, data, sources)
    Path(str(out) + ".json").write_text(json.dumps(info, indent=2) + "\n")
    return info


def load_pack(path, split, sources=None):
    """A split of the pack as motion.dataset.ClipSet (float32, 60 Hz), optionally only some sources."""
    from motion import dataset as ds
    try:
        z = np.load(path, allow_pickle=False)
        info = json.loads(str(z["info"]))
    except (OSError, ValueError, KeyError) as e:
        raise PackError(f"{path}: not an edgepose training pack ({e}); build one: python -m motion.pack") from e
    if info.get("format") != FORMAT:
        raise PackError(f"{path}: format {info.get('format')!r}, this code reads {FORMAT}; rebuild: python -m motion.pack")
    if f"{split}_rot" not in z:
        raise PackError(f"{path}: no {split!r} split")
    names, lengths, stored, steps = (z[f"{split}_{k}"] for k in ("names", "lengths", "stored", "steps"))
    J = info["splits"][split]["joints"]
    q_parts = _decompress(z[f"{split}_rot"], np.int16, J * 4, stored)
    p_parts = _decompress(z[f"{split}_root"], np.int32, 3, stored)
    contacts = np.unpackbits(z[f"{split}_contacts"])[:int(lengths.sum()) * 2].reshape(-1, 2).astype(np.float32)
    keep = np.ones(len(names), bool)
    if sources:
        folders = tuple(f for s in sources for f in ds.SOURCE_FOLDERS[s])
        keep = np.array([str(n).startswith(folders) for n in names])
    rots, roots, cons, kept = [], [], [], []
    starts60 = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    for i in np.flatnonzero(keep):
        q = q_parts[i].reshape(-1, J, 4) / ROT_SCALE
        q /= np.linalg.norm(q, axis=-1, keepdims=True)
        rot, root = _expand(q, p_parts[i] / ROOT_SCALE, int(steps[i]), int(lengths[i]))
        rots.append(rot.astype(np.float32))
        roots.append(root.astype(np.float32))
        cons.append(contacts[starts60[i]:starts60[i] + lengths[i]])
        kept.append(str(names[i]))
    starts = np.cumsum([0] + [len(r) for r in roots[:-1]]).astype(np.int64)
    return ds.ClipSet(kept, starts, np.concatenate(rots), np.concatenate(roots), np.concatenate(cons))


def pack_error_mm(path, data, sources=None, frames=20000, seed=0):
    """What the pack's rounding costs: FK joint positions (world, from the root) of the pack's clips
    against the cache built from the BVH files, on `frames` random frames of each split.
    -> {split: {"mean": mm, "max": mm}}."""
    from motion import dataset as ds
    from motion.synth import world_pose
    rng = np.random.default_rng(seed)
    out = {}
    for split in ("train", "val"):
        ref, got = ds.build(data, split, sources), load_pack(path, split, sources)
        if len(ref.root) != len(got.root) or not np.array_equal(ref.contacts, got.contacts):
            raise PackError(f"{split}: the pack does not hold the same frames as the mocap cache")
        f = rng.integers(0, len(ref.root), frames)
        _, a = world_pose(ref.rotations[f].astype(np.float64), ref.root[f].astype(np.float64))
        _, b = world_pose(got.rotations[f].astype(np.float64), got.root[f].astype(np.float64))
        err = np.linalg.norm(a - b, axis=-1) * 1000
        out[split] = {"mean": float(err.mean()), "max": float(err.max())}
    return out


def main(argv=None):
    from motion import dataset as ds
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--out", default=str(DEFAULT_PACK))
    ap.add_argument("--sources", nargs="*", default=None, choices=sorted(ds.SOURCE_FOLDERS))
    a = ap.parse_args(argv)
    with Progress(1, "pack") as bar:
        info = build_pack(a.data, a.out, a.sources)
        bar.update()
    for split, s in info["splits"].items():
        print(f"{split}: {s['clips']} clips, {s['minutes']:.1f} min, {s['stored_frames']:,} frames stored; "
              f"FK error {info['error_mm'][split]['mean']:.3f} mm mean, {info['error_mm'][split]['max']:.3f} max")
    print(f"wrote {a.out}: {info['bytes'] / 2**20:.1f} MiB, sha256 {info['sha256']}; details in {a.out}.json")


if __name__ == "__main__":
    main()
