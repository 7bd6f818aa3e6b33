"""Motion-capture clips -> canonical motions at the model rate, cached, and training windows.

Reads `MANIFEST.tsv` from the mocap folder; `--sources` keeps e.g. CMU only (Bandai is CC BY-NC).
"""
import argparse
import csv
import functools
import hashlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edge import imus, quat
from motion.bvh import BvhError
from motion.contacts import contact_labels
from edge.features import orientation_features, sequence_features
from edge.progress import Progress
from motion import augment
from motion.augment import Augment
from motion.retarget import frames_at, load_motion
from motion.synth import DeviceNoise, synthesize_from_pose, wear, world_pose
from edge.skeleton import FEET, HEAD, PREDICTED, TOES

# --sources groups -> folders of ../shared/mocap. CMU terms: cmu, daz; CC BY-NC 4.0: bandai; CC BY-SA 3.0: hdm05.
SOURCE_FOLDERS = {
    "cmu": ("cmu_amc2bvh", "cmu_cgspeed_mb"),                   # CMU originals (incl. 135 karate) and cgspeed's BVH
    "daz": ("cmu_daz_ateliercircle", "cmu_daz_papagina", "cmu_fbx_daz"),    # CMU motion on the Daz skeleton
    "bandai": ("bandai_namco_ccbync",),
    "hdm05": ("hdm05_ccbysa",),
}
SOURCE_LICENCES = {"cmu": "CMU terms (free for research and commercial use; no resale)", "daz": "CMU terms + MIT",
                   "bandai": "CC BY-NC 4.0 (non-commercial)", "hdm05": "CC BY-SA 3.0 (share-alike)"}
# --sources also takes a single folder (e.g. cmu_fbx_daz), under its group's licence
FOLDER_GROUP = {f: g for g, folders in SOURCE_FOLDERS.items() for f in folders}
SOURCES = sorted(SOURCE_FOLDERS) + sorted(FOLDER_GROUP)


def source_folders(sources):
    """--sources (groups or folders) -> the mocap folders they name."""
    return tuple(f for s in sources for f in SOURCE_FOLDERS.get(s, (s,)))


def source_licences(sources):
    return {s: SOURCE_LICENCES[FOLDER_GROUP.get(s, s)] for s in sources}


FPS = 60.0


def read_manifest(root):
    """Rows of MANIFEST.tsv as dicts, or None when the folder has none."""
    path = Path(root) / "MANIFEST.tsv"
    if not path.exists():
        return None
    with open(path, newline="") as f:
        return list(csv.DictReader(f, delimiter="\t"))


def clip_paths(root, split=None, sources=None):
    root = Path(root)
    rows = read_manifest(root)
    if rows is None:
        return sorted(root.rglob("*.bvh"))
    folders = None if not sources else source_folders(sources)
    return [root / r["file"] for r in rows
            if (split is None or r["split"] == split) and (folders is None or r["file"].startswith(folders))]


def _load(path, conventions=True):
    try:
        m = load_motion(path, FPS, conventions)
        return str(path), m.rotations.astype(np.float32), m.root.astype(np.float32)
    except BvhError as e:
        return str(path), None, str(e)


@dataclass
class ClipSet:
    """Concatenated clips: rotations [F,J,4], root [F,3], contacts [F,2], and clip start offsets; with
    each clip's people ("unseen" where its performer has no clip in train, else "seen"; None: unknown)
    and subject (the manifest's performer, e.g. "cmu:69"; None: unknown)."""
    names: list
    starts: np.ndarray
    rotations: np.ndarray
    root: np.ndarray
    contacts: np.ndarray
    people: np.ndarray = None
    subjects: np.ndarray = None

    def lengths(self):
        return np.diff(np.append(self.starts, len(self.root)))

    def subset(self, keep):
        """The clips where keep [clips] is true, as a ClipSet of their own."""
        idx = np.flatnonzero(keep)
        frames = np.concatenate([np.arange(s, s + n) for s, n in zip(self.starts[idx], self.lengths()[idx],
                                                                     strict=True)])
        lengths = self.lengths()[idx]
        return ClipSet([self.names[i] for i in idx], np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64),
                       self.rotations[frames], self.root[frames], self.contacts[frames],
                       None if self.people is None else self.people[idx],
                       None if self.subjects is None else self.subjects[idx])


def clip_people(root, names):
    """Each clip's people (motion.takes.people_of: "unseen" or "seen") from the folder's MANIFEST.tsv."""
    from motion.takes import people_of
    rows = read_manifest(root)
    if rows is None:
        return None
    who = people_of(rows)
    return np.array([who.get(str(Path(n).relative_to(root)), "seen") for n in names])


def clip_subjects(root, names):
    """Each clip's subject (the manifest's performer column) from the folder's MANIFEST.tsv, or None."""
    rows = read_manifest(root)
    if rows is None:
        return None
    who = {r["file"]: r.get("subject") or "unknown" for r in rows}
    return np.array([who.get(str(Path(n).relative_to(root)), "unknown") for n in names])


def build(root, split, sources=None, cache_dir=".cache", workers=2, conventions=True):
    """A split's clips as a ClipSet, from the mocap folder `root` through a cache of its retargeted clips
    (a training pack is read by motion.pack.read_clips, which decides between the two). conventions=False
    leaves each source's skeleton conventions in (motion.neutrals): the clips as cache v7 had them, for
    the side-by-side run that measures what taking them out does."""
    paths = clip_paths(root, split, sources)
    key = hashlib.sha1(("v8|" if conventions else "v7|").encode() + "|".join(map(str, paths)).encode()).hexdigest()[:12]
    cache = Path(cache_dir) / f"clips-{split}-{key}.npz"
    if cache.exists():
        d = np.load(cache, allow_pickle=False)
        names = list(d["names"])
        return ClipSet(names, d["starts"], d["rotations"], d["root"], d["contacts"], clip_people(root, names),
                       clip_subjects(root, names))
    names, rots, roots, cons = [], [], [], []
    with ProcessPoolExecutor(workers) as ex, Progress(len(paths), f"load {split}") as bar:
        for path, rot, root_pos in ex.map(functools.partial(_load, conventions=conventions), paths, chunksize=8):
            bar.update()
            if rot is None:
                print(f"skipped: {root_pos}")
                continue
            _, pos = world_pose(rot.astype(np.float64), root_pos.astype(np.float64))
            names.append(path)
            rots.append(rot)
            roots.append(root_pos)
            cons.append(contact_labels(pos[:, FEET], FPS))
    starts = np.cumsum([0] + [len(r) for r in roots[:-1]])
    cs = ClipSet(names, starts, np.concatenate(rots), np.concatenate(roots), np.concatenate(cons),
                 clip_people(root, names), clip_subjects(root, names))
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.savez(cache, names=np.array(names), starts=starts, rotations=cs.rotations, root=cs.root, contacts=cs.contacts)
    return cs


def window_starts(cs: ClipSet, window):
    """Every valid window start (global frame index), stride 1."""
    out = [s + np.arange(n - window + 1) for s, n in zip(cs.starts, cs.lengths(), strict=True) if n >= window]
    return np.concatenate(out)


PERSON_RULES = ("frames", "people", "sqrt", "capped")


def people_in(subject):
    """How many people a manifest subject is: "bandai:unlabelled(3 actors)" is three, any other one."""
    import re
    m = re.search(r"\((\d+) actors?\)", str(subject))
    return int(m.group(1)) if m else 1


class WindowDraw:
    """Which window starts a batch takes: uniformly over frames (rule "frames", the recipe until v0.5.1),
    or by person, each person's share of the windows set by the rule and spread evenly over that person's
    windows. A person's share, by rule: "people" the same for everyone; "sqrt" the square root of their
    minutes; "capped" their minutes up to `cap_minutes`. A subject that is several unlabelled people
    (Bandai's three actors) counts as that many people, each with an equal part of its minutes."""

    def __init__(self, cs: ClipSet, starts, rule="frames", cap_minutes=10.0):
        if rule not in PERSON_RULES:
            raise ValueError(f"window rule {rule!r}: one of {', '.join(PERSON_RULES)}")
        self.starts, self.rule = np.asarray(starts), rule
        self.cdf, self.shares = None, None
        if rule == "frames":
            return
        if cs.subjects is None:
            raise ValueError("drawing windows by person needs each clip's subject: read the mocap folder (its "
                             "MANIFEST.tsv), or rebuild the pack (python -m motion.pack)")
        clip = np.searchsorted(cs.starts, self.starts, side="right") - 1
        subject = cs.subjects[clip]
        names, of_start = np.unique(subject, return_inverse=True)
        n_starts = np.bincount(of_start, minlength=len(names)).astype(np.float64)
        frames = np.array([cs.lengths()[cs.subjects == n].sum() for n in names], np.float64)
        people = np.array([people_in(n) for n in names], np.float64)
        person_min = frames / FPS / 60 / people
        per_person = {"people": np.ones_like(person_min), "sqrt": np.sqrt(person_min),
                      "capped": np.minimum(person_min, cap_minutes)}[rule]
        weight = per_person * people                       # the subject's share, before normalising
        weight /= weight.sum()
        p = weight[of_start] / n_starts[of_start]
        self.cdf = np.cumsum(p)
        self.cdf /= self.cdf[-1]
        by_frames = n_starts / n_starts.sum()
        self.shares = sorted(zip(names, people, person_min * people, by_frames, weight, strict=True),
                             key=lambda r: -r[4])

    def draw(self, rng, n):
        if self.cdf is None:
            return rng.choice(self.starts, n)
        return self.starts[np.minimum(np.searchsorted(self.cdf, rng.random(n)), len(self.starts) - 1)]

    def table(self):
        """The share of the windows each subject gets, as lines to print at the start of a run."""
        if self.shares is None:
            return [f"windows drawn uniformly over frames ({len(self.starts):,} starts)"]
        lines = [f"windows drawn by person, rule {self.rule!r}: subject, people, minutes, share by frames -> share"]
        lines += [f"  {n:32s} {int(k):2d} {m:7.1f} min {f * 100:6.2f} % -> {w * 100:6.2f} %"
                  for n, k, m, f, w in self.shares]
        return lines


def vigorous_starts(cs: ClipSet, starts, window, height=0.35, chunk=50_000):
    """The window starts whose ground truth lifts a toe at least `height` metres off the floor (kicks,
    high steps, jumps, dance): about 7 % of `train`'s windows, 1.5 % above 0.9 m."""
    toe = np.zeros(len(cs.root))
    for i in range(0, len(toe), chunk):
        _, pos = world_pose(cs.rotations[i:i + chunk].astype(np.float64), cs.root[i:i + chunk].astype(np.float64))
        toe[i:i + chunk] = pos[:, TOES, 1].max(1)
    highest = np.lib.stride_tricks.sliding_window_view(toe, window).max(1)
    return starts[highest[starts] >= height]


def random_imus(rng, window, batch, flaky=1 / 3, p_drop=0.01, outage=100):
    """Which extra IMUs each window wears, and when each one is heard (DragPoser's variable sets and
    faulty sensors): a quarter of the windows wear none, a third one of the common sets, the rest a
    random subset. In `flaky` of the windows every worn IMU follows DragPoser's protocol (each frame it
    drops with probability p_drop and returns `outage` frames later: a 60-frame window sees it come,
    go or stay away), as the window's slice of a longer stream; in the others a worn IMU goes silent
    once with probability 0.3, for 5-45 frames (past 15 frames the synchroniser calls it lost and
    fades its flag). -> worn [B,7], alive [W,B,7]."""
    K = imus.NUM_IMUS
    worn = np.zeros((batch, K))
    kind = rng.random(batch)
    sets = [imus.mask(s) for s in imus.COMMON_SETS]
    for b in np.flatnonzero((kind >= 0.25) & (kind < 0.6)):
        worn[b] = sets[rng.integers(len(sets))]
    rand = kind >= 0.6
    worn[rand] = rng.random((int(rand.sum()), K)) < 0.5
    drop = (rng.random((batch, K)) < 0.3) & (worn > 0)
    start, length = rng.integers(0, window, (batch, K)), rng.integers(5, 46, (batch, K))
    t = np.arange(window)[:, None, None]
    silent = drop & (t >= start) & (t < start + length)
    # DragPoser's protocol (sec. 4.4): drops in the `outage` frames before the window count too
    protocol = (rng.random(batch) < flaky)[None, :, None]
    drops = rng.random((window + outage, batch, K)) < p_drop
    since = np.cumsum(drops, axis=0)
    down = (since[outage:] - since[:window]) > 0            # a drop in the last `outage` frames
    alive = (worn[None] > 0) & ~np.where(protocol, down, silent)
    return worn, alive


def draw_batch(rng, starts, window, noise: DeviceNoise = None, imu_noise: imus.ImuNoise = None, with_imus=True,
               augment: Augment = None):
    """Every random number of a batch of windows starting at `starts` [B], in the order make_batch has
    always drawn them: the heading and floor shift, the device noise, which IMUs are worn and heard,
    and their noise; then, with `augment`, which windows are mirrored and their tempo (drawn last, so a
    run without it draws what it always drew). render_batch makes the batch from them; models.batches
    draws the same on a device."""
    B = len(starts)
    d = {"starts": np.asarray(starts), "yaw": rng.uniform(-np.pi, np.pi, B),
         "shift": np.concatenate([rng.uniform(-2, 2, (B, 1)), np.zeros((B, 1)), rng.uniform(-2, 2, (B, 1))], axis=1)}
    if noise is not None:
        d["device"] = noise.draw(rng, window, (B,))
    if with_imus:
        d["worn"], d["alive"] = random_imus(rng, window, B)
        if imu_noise is not None:
            d["imu"] = imu_noise.draw(rng, (window, B, imus.NUM_IMUS))
    if augment is not None:
        d.update(augment.draw(rng, B))
    return d


def window_motion(cs: ClipSet, d, window):
    """The canonical motion of each window [W,B,...]: rotations, root and foot contacts, read at the
    window's tempo (d["speed"], through the resampler the clips are read with) and mirrored where
    d["mirror"] says (motion.augment)."""
    if "speed" in d:
        t = d["starts"][None, :] + np.arange(window)[:, None] * d["speed"][None, :]
        rot, root = frames_at(cs.rotations, cs.root, t)
        contacts = cs.contacts[np.rint(t).astype(np.int64)]
    else:
        idx = d["starts"][None, :] + np.arange(window)[:, None]          # [W,B]
        rot, root, contacts = cs.rotations[idx].astype(np.float64), cs.root[idx].astype(np.float64), cs.contacts[idx]
    if "mirror" in d and d["mirror"].any():
        m = d["mirror"]
        rot[:, m] = augment.mirror_rotations(rot[:, m])
        root[:, m] = augment.mirror_root(root[:, m])
        contacts = contacts.copy()
        contacts[:, m] = augment.mirror_contacts(contacts[:, m])
    return rot, root, contacts


def render_batch(cs: ClipSet, d, window, noise: DeviceNoise = None, imu_noise: imus.ImuNoise = None, hands=None,
                 orientations=False):
    """The batch that draw_batch's numbers `d` make of the clips (deterministic): time-major [W,B,...]
    model inputs and targets. With `orientations` also "orient", the headset's and controllers'
    orientation features the decoder's upper-body head reads (models.train_upper); `hands`: a function of
    the batch's Signals that returns them with the controllers turned about the wrists (its augmentation)."""
    rot, root, contacts = window_motion(cs, d, window)          # [W,B,J,4], [W,B,3], [W,B,2]
    # Random heading and floor position: the data should not teach the model where the room is.
    yaw = quat.from_yaw(d["yaw"])
    rot = rot.copy()
    rot[:, :, 0] = quat.mul(yaw[None], rot[:, :, 0])
    root = quat.rotate(yaw[None], root) + d["shift"][None]
    world_rot, gt_pos = world_pose(rot, root)
    sig = synthesize_from_pose(world_rot, gt_pos, FPS)
    if "device" in d:
        sig = noise.apply_drawn(sig, FPS, d["device"])
    if "worn" in d:
        worn, alive = d["worn"], d["alive"]
        if "mirror" in d:           # the IMU on the person's left foot is on the mirror image's right foot
            m = d["mirror"]
            worn, alive = np.where(m[:, None], augment.mirror_imus(worn), worn), \
                np.where(m[None, :, None], augment.mirror_imus(alive), alive)
        sig = wear(sig, worn[None], FPS, alive=alive, noise=imu_noise, drawn=d.get("imu"))
    if hands is not None:
        sig = hands(sig)
    feats, points, yaw_q = sequence_features(sig, FPS)
    inv_yaw = quat.inv(yaw_q)[..., None, :]
    gt_rel = quat.rotate(inv_yaw, gt_pos - gt_pos[..., HEAD:HEAD + 1, :])   # head-anchored, character frame
    root_local = quat.mul(quat.inv(yaw_q), sig.waist_rot)                 # puck orientation in the yaw frame
    local_m = quat.to_matrix(rot[..., PREDICTED, :])
    out = {
        "features": feats.astype(np.float32),
        "gt_rel": gt_rel.astype(np.float32),
        "root_rot": quat.to_matrix(root_local).astype(np.float32),
        "rot6d": quat.matrix_to_6d(local_m).reshape(local_m.shape[:-3] + (-1,)).astype(np.float32),
        "contacts": contacts,
        "anchor_y": points[..., 0, 1].astype(np.float32),        # the tracked head joint's height (floor terms)
    }
    if orientations:
        out["orient"] = orientation_features(sig.head_rot, sig.hand_rot, yaw_q).astype(np.float32)
    return out


def make_batch(cs: ClipSet, starts, window, rng, noise: DeviceNoise = None, imu_noise: imus.ImuNoise = None,
               with_imus=True, hands=None, orientations=False, augment: Augment = None):
    """Time-major batch [W,B,...] of model inputs and targets, with device noise synthesised per window
    and a random set of extra IMUs (random_imus) unless with_imus is False (the 4-point case). The
    reference for models.batches, which makes the same on an accelerator."""
    return render_batch(cs, draw_batch(rng, starts, window, noise, imu_noise, with_imus, augment), window, noise,
                        imu_noise, hands, orientations)


def pose_batch(cs: ClipSet, frames):
    """Ground-truth poses for the autoencoder: local positions [B,63], root rotation in the yaw frame [B,3,3]."""
    from edge.plausibility import local_pose
    rot = cs.rotations[frames].astype(np.float64)
    root = cs.root[frames].astype(np.float64)
    rm, pos = world_pose(rot, root)
    local, root_local = local_pose(pos, rm[:, 0])
    return {"positions": local.reshape(len(frames), -1).astype(np.float32), "root_rot": root_local.astype(np.float32)}


def main():
    ap = argparse.ArgumentParser(description="Build the canonical-motion cache from the mocap folder.")
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--sources", nargs="*", default=None, choices=SOURCES)
    a = ap.parse_args()
    for split in ("train", "val"):
        cs = build(a.data, split, a.sources)
        print(split, len(cs.names), "clips", len(cs.root), "frames", f"{len(cs.root) / FPS / 60:.1f} min")


if __name__ == "__main__":
    main()
