"""The training pack: the whole retargeted train and val set in one file that travels (to an accelerator).

    python -m motion.pack [--data ../shared/mocap] [--out .cache/pack/edgepose-pack.npz] [--sources ...]

`models.train --data PACK` (through read_clips, which also reads a mocap folder) reads it instead of the mocap folder. What it holds
is what training reads, motion.dataset's ClipSet per split, in this form:
- rotations: each joint's local quaternion in Q13 integers (1/8192; the error is measured at build time
  as FK joint positions on every frame, in mm, and printed and recorded); each clip keeps its own
  frames at its own rate (24, 30 or 60 fps) and is resampled to 60 Hz on load with the same
  motion.retarget.resample that made the cache; second differences in time per clip, channel by
  channel, LZMA-compressed.
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
from motion import dataset as ds

ROT_SCALE = 8192.0          # Q13 quaternion components
ROOT_SCALE = 10000.0        # 0.1 mm
DEFAULT_PACK = Path(".cache/pack/edgepose-pack.npz")
FORMAT = "edgepose-pack/2"      # 2: each clip's own frames at its own rate (24, 30 or 60 fps)


class PackError(ValueError):
    """A pack file that is not one, or that does not hold what was asked for."""


def is_pack(path):
    return Path(path).is_file() and str(path).endswith(".npz")


def read_clips(data, split, sources=None, conventions=True):
    """A split's clips as a motion.dataset.ClipSet from `data`, a training pack or a mocap folder (through
    motion.dataset.build's cache of retargeted clips): what training reads, wherever it runs.
    conventions=False (each source's skeleton conventions left in) reads a mocap folder only."""
    if not is_pack(data):
        return ds.build(data, split, sources, conventions=conventions)
    if not conventions:
        raise PackError(f"{data}: a pack holds the clips with the conventions taken out; read the mocap folder")
    return load_pack(data, split, sources)


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


def _read_native(path):
    """A clip on the canonical skeleton at its own frame rate (what motion.retarget.load_motion
    resamples to 60 Hz): (rotations [F,J,4], root [F,3], fps as its file says)."""
    from motion import bvh
    from motion.retarget import retarget
    m, _ = retarget(bvh.load(path))
    return m.rotations, m.root, m.fps


def _native_frames(data, cs, names, rows, workers=2):
    """Every clip's own frames, not the 60 Hz ones: a 60 fps clip is the cache itself; any other (30 fps
    Bandai, whose files say 0.0333333 s a frame, and the 24 fps CMU library) is read again from its
    file, since the 60 Hz grid does not hit its frames exactly. -> (rotations, roots, fps) per clip."""
    from concurrent.futures import ProcessPoolExecutor
    manifest_fps = {r["file"]: float(r["fps"]) for r in rows}
    rots, roots, fps = [None] * len(names), [None] * len(names), np.full(len(names), 60.0)
    reread = [i for i, n in enumerate(names) if abs(manifest_fps[n] - 60) > 1e-3]
    with ProcessPoolExecutor(workers) as ex, Progress(len(reread), "own frames") as bar:
        for i, (rot, root, f) in zip(reread, ex.map(_read_native, [Path(data) / names[i] for i in reread],
                                                     chunksize=8), strict=True):
            rots[i], roots[i], fps[i] = rot, root, f
            bar.update()
    for i, (s, n) in enumerate(zip(cs.starts, cs.lengths(), strict=True)):
        if rots[i] is None:
            rots[i], roots[i] = cs.rotations[s:s + n], cs.root[s:s + n]
        if _frames_60hz(len(roots[i]), fps[i]) != n:
            raise PackError(f"{names[i]}: {len(roots[i])} frames at {fps[i]:g} fps do not make the {n} cached "
                            "60 Hz frames (the cache is older than the file? delete .cache/clips-*.npz)")
    return rots, roots, fps


def _frames_60hz(n, fps):
    """How many 60 Hz frames motion.retarget.resample makes of n frames at fps."""
    return n if abs(fps - 60) < 1e-3 else len(np.arange(0.0, (n - 1) / fps + 1e-9, 1 / 60))


def _expand(q_native, root_native, fps):
    """A clip's own frames back to 60 Hz, exactly as motion.retarget.resample made the cached clip from
    its file (slerp for rotations, lerp for the root); pack_error_mm measures what the rounding costs."""
    from motion.retarget import Motion, resample
    m = resample(Motion(q_native, root_native, fps), 60.0)
    return m.rotations, m.root


def build_pack(data, out=DEFAULT_PACK, sources=None):
    """Read (or reuse the cache of) the retargeted train and val sets and write the pack. Returns its info."""
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
        rots, roots, fps = _native_frames(data, cs, names, rows)
        J = cs.rotations.shape[1]
        q_int = [np.round(r.reshape(len(r), -1) * ROT_SCALE) for r in rots]
        p_int = [np.round(r * ROOT_SCALE) for r in roots]
        arrays[f"{split}_rot"] = _compress(q_int, np.int16)
        arrays[f"{split}_root"] = _compress(p_int, np.int32)
        arrays[f"{split}_contacts"] = np.packbits(cs.contacts.astype(bool), axis=None)
        arrays[f"{split}_lengths"] = cs.lengths().astype(np.int64)
        arrays[f"{split}_stored"] = np.array([len(r) for r in rots], np.int64)
        arrays[f"{split}_fps"] = fps
        arrays[f"{split}_names"] = np.array(names)
        arrays[f"{split}_people"] = cs.people          # unseen / seen (motion.takes.people_of): val is chosen on unseen
        arrays[f"{split}_subjects"] = cs.subjects      # the performer: training draws windows by person
        info["splits"][split] = {"clips": len(cs.names), "frames_60hz": int(len(cs.root)),
                                 "stored_frames": int(sum(len(r) for r in rots)), "joints": int(J),
                                 "minutes": len(cs.root) / 3600,
                                 "unseen_people_minutes": float(cs.lengths()[cs.people == "unseen"].sum() / 3600)}
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
    try:
        z = np.load(path, allow_pickle=False)
        info = json.loads(str(z["info"]))
    except (OSError, ValueError, KeyError) as e:
        raise PackError(f"{path}: not an edgepose training pack ({e}); build one: python -m motion.pack") from e
    if info.get("format") != FORMAT:
        raise PackError(f"{path}: format {info.get('format')!r}, this code reads {FORMAT}; rebuild: python -m motion.pack")
    if f"{split}_rot" not in z:
        raise PackError(f"{path}: no {split!r} split")
    names, lengths, stored, fps = (z[f"{split}_{k}"] for k in ("names", "lengths", "stored", "fps"))
    J = info["splits"][split]["joints"]
    q_parts = _decompress(z[f"{split}_rot"], np.int16, J * 4, stored)
    p_parts = _decompress(z[f"{split}_root"], np.int32, 3, stored)
    contacts = np.unpackbits(z[f"{split}_contacts"])[:int(lengths.sum()) * 2].reshape(-1, 2).astype(np.float32)
    keep = np.ones(len(names), bool)
    if sources:
        folders = ds.source_folders(sources)
        keep = np.array([str(n).startswith(folders) for n in names])
    people = z[f"{split}_people"] if f"{split}_people" in z else None
    subjects = z[f"{split}_subjects"] if f"{split}_subjects" in z else None     # packs before 7 December have none
    rots, roots, cons, kept = [], [], [], []
    starts60 = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    for i in np.flatnonzero(keep):
        q = q_parts[i].reshape(-1, J, 4) / ROT_SCALE
        q /= np.linalg.norm(q, axis=-1, keepdims=True)
        rot, root = _expand(q, p_parts[i] / ROOT_SCALE, float(fps[i]))
        if len(root) != lengths[i]:
            raise PackError(f"{path}: {names[i]} expands to {len(root)} frames, the pack says {lengths[i]}")
        rots.append(rot.astype(np.float32))
        roots.append(root.astype(np.float32))
        cons.append(contacts[starts60[i]:starts60[i] + lengths[i]])
        kept.append(str(names[i]))
    starts = np.cumsum([0] + [len(r) for r in roots[:-1]]).astype(np.int64)
    return ds.ClipSet(kept, starts, np.concatenate(rots), np.concatenate(roots), np.concatenate(cons),
                      None if people is None else people[keep], None if subjects is None else subjects[keep])


def pack_error_mm(path, data, sources=None, chunk=100_000):
    """What the pack's rounding costs: FK joint positions (world, from the root) of every frame of the
    pack's clips against the cache built from the BVH files.
    -> {split: {"mean": mm, "max": mm, "worst_clip": name}} (a frame's error is its worst joint's)."""
    from motion.synth import world_pose
    out = {}
    for split in ("train", "val"):
        ref, got = ds.build(data, split, sources), load_pack(path, split, sources)
        if len(ref.root) != len(got.root) or not np.array_equal(ref.contacts, got.contacts):
            raise PackError(f"{split}: the pack does not hold the same frames as the mocap cache")
        worst = np.zeros(len(ref.root))
        for i in range(0, len(ref.root), chunk):
            f = slice(i, i + chunk)
            _, a = world_pose(ref.rotations[f].astype(np.float64), ref.root[f].astype(np.float64))
            _, b = world_pose(got.rotations[f].astype(np.float64), got.root[f].astype(np.float64))
            worst[f] = np.linalg.norm(a - b, axis=-1).max(-1) * 1000
        clip = np.searchsorted(ref.starts, int(worst.argmax()), side="right") - 1
        out[split] = {"mean": float(worst.mean()), "max": float(worst.max()),
                      "worst_clip": os.path.relpath(ref.names[clip], data)}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--out", default=str(DEFAULT_PACK))
    ap.add_argument("--sources", nargs="*", default=None, choices=ds.SOURCES)
    a = ap.parse_args(argv)
    with Progress(1, "pack") as bar:
        info = build_pack(a.data, a.out, a.sources)
        bar.update()
    for split, s in info["splits"].items():
        print(f"{split}: {s['clips']} clips, {s['minutes']:.1f} min, {s['stored_frames']:,} frames stored; "
              f"FK error (worst joint of a frame) {info['error_mm'][split]['mean']:.3f} mm mean, "
              f"{info['error_mm'][split]['max']:.3f} max ({info['error_mm'][split]['worst_clip']})")
    print(f"wrote {a.out}: {info['bytes'] / 2**20:.1f} MiB, sha256 {info['sha256']}; details in {a.out}.json")


if __name__ == "__main__":
    main()
