"""A take: tracker signals for a clip plus its ground-truth joint positions, from a BVH file or a sample file.

`edge eval` and the simulator read takes. BVH files go through the same retargeting and signal
synthesis as training; sample files (.npz) carry signals and ground truth and no BVH.
"""
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from motion.bvh import BvhError
from edge.signals import Signals
from motion.synth import synthesize, world_pose
from edge.skeleton import JOINT_NAMES

FPS = 60.0


from edge.imus import IMU_LOCATIONS


@dataclass
class Take:
    name: str
    signals: Signals
    gt_pos: np.ndarray   # [T,J,3] world metres
    fps: float
    imu: dict = None     # extra IMU location (edge.imus) -> the true world orientation [T,4] of its segment

    @property
    def frames(self):
        return self.signals.frames


def _imus_of(signals):
    return {name: signals.imu_rot[:, k] for k, name in enumerate(IMU_LOCATIONS)}


def from_bvh(path, fps=FPS, rng=None, noise=None, conventions=True):
    """A BVH clip retargeted (conventions=False: with its source's skeleton conventions left in, the
    ruler before motion.neutrals), its devices synthesised."""
    from motion.retarget import load_motion
    m = load_motion(path, fps, conventions)
    _, pos = world_pose(m.rotations, m.root)
    sig = synthesize(m.rotations, m.root, fps, rng, noise)
    return Take(str(path), sig, pos, fps, _imus_of(sig))


def save_sample(path, take, credit):
    np.savez_compressed(path, fps=take.fps, name=take.name, credit=credit, joint_names=np.array(JOINT_NAMES),
                        gt_pos=take.gt_pos.astype(np.float32), **take.signals.as_dict("sig_"))


def from_sample(path):
    try:
        d = np.load(path, allow_pickle=False)
        names = [str(n) for n in d["joint_names"]]
        if names != list(JOINT_NAMES):
            raise BvhError(f"{path}: sample was made for a different skeleton ({len(names)} joints)")
        sig = Signals.from_dict(d, "sig_")
        if "sig_imu_rot" in d.files:         # every location's segment orientation is in the signals
            imu = _imus_of(sig)
        else:                                # older files: the extra trackers they recorded (chest, feet)
            imu = {k[4:]: d[k].astype(np.float64) for k in d.files if k.startswith("imu_")}
        return Take(str(d["name"]), sig, d["gt_pos"].astype(np.float64), float(d["fps"]), imu)
    except (OSError, KeyError, ValueError) as e:
        raise BvhError(f"{path}: not a readable edgepose sample file ({e})") from None


PEOPLE = ("unseen", "seen")


def people_of(rows):
    """MANIFEST.tsv rows -> {file: "unseen" | "seen"}: a val clip's performer is unseen when their
    subject has no clip in `train` (CMU subjects and HDM05's mm held out whole); seen otherwise
    (Bandai's actors fill both splits). Train clips are "seen"."""
    in_train = {r.get("subject") for r in rows if r.get("split") == "train"}
    return {r["file"]: "seen" if r.get("subject") in in_train else "unseen" for r in rows}


def _manifest_rows(folder):
    import csv
    with open(folder / "MANIFEST.tsv", newline="") as f:
        return list(csv.DictReader(f, delimiter="\t"))


def find_clips(paths, split=None, people=None):
    """Expand files and folders into a list of BVH/sample files; folders with a MANIFEST.tsv filter by
    split and, with `people` ("unseen" or "seen", see people_of), by whether the model saw the performer."""
    if people not in (None, *PEOPLE):
        raise ValueError(f"people {people!r}: choose one of {', '.join(PEOPLE)} (or all)")
    out = []
    for p in map(Path, paths):
        if p.is_dir():
            if (p / "MANIFEST.tsv").exists():
                rows = _manifest_rows(p)
                seen = people_of(rows)
                out += [p / r["file"] for r in rows if (split is None or r.get("split") == split)
                        and (people is None or seen[r["file"]] == people)]
            else:
                if people:
                    raise ValueError(f"{p}: no MANIFEST.tsv, so nothing says whose clips are unseen")
                out += sorted(list(p.rglob("*.bvh")) + list(p.rglob("*.npz")))
        elif p.exists():
            out.append(p)
        else:
            hint = ("; the motion capture lives beside the project in ../shared/mocap (BVH files with a "
                    "MANIFEST.tsv of train/val splits, not in this repository), or give BVH files, folders "
                    "of them, or edgepose sample .npz files such as samples/cmu_09_12_walk.npz")
            raise FileNotFoundError(f"no such file or folder: {p}{hint}")
    return out


def people_of_files(paths, files):
    """{file: "unseen" | "seen"} for the files that come from a folder of `paths` with a MANIFEST.tsv."""
    out = {}
    for p in map(Path, paths):
        if p.is_dir() and (p / "MANIFEST.tsv").exists():
            out.update({p / f: who for f, who in people_of(_manifest_rows(p)).items()})
    return {f: out[Path(f)] for f in files if Path(f) in out}


def load_take(path, **kw):
    return from_sample(path) if str(path).endswith(".npz") else from_bvh(path, **kw)
