"""A take: tracker signals for a clip plus its ground-truth joint positions, from a BVH file or a sample file.

`edge eval` and the simulator read takes. BVH files go through the same retargeting and signal
synthesis as training; sample files (.npz) carry signals and ground truth and no BVH.
"""
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edge.bvh import BvhError
from edge.signals import Signals, synthesize, world_pose
from edge.skeleton import JOINT_NAMES

FPS = 60.0


# Extra IMU trackers a take can carry besides the waist puck: tracker name -> the joint it sits on.
EXTRA_IMUS = {"chest": "chest", "l_foot": "l_ankle", "r_foot": "r_ankle"}


@dataclass
class Take:
    name: str
    signals: Signals
    gt_pos: np.ndarray   # [T,J,3] world metres
    fps: float
    imu: dict = None     # extra tracker name -> world orientation [T,4] of its body part (see EXTRA_IMUS)

    @property
    def frames(self):
        return self.signals.frames


def from_bvh(path, fps=FPS, rng=None, noise=None):
    from edge import quat
    from edge.retarget import load_motion
    from edge.skeleton import JOINT
    m = load_motion(path, fps)
    rot, pos = world_pose(m.rotations, m.root)
    imu = {name: quat.from_matrix(rot[:, JOINT[joint]]) for name, joint in EXTRA_IMUS.items()}
    return Take(str(path), synthesize(m.rotations, m.root, fps, rng, noise), pos, fps, imu)


def save_sample(path, take, credit):
    imu = {f"imu_{k}": v.astype(np.float32) for k, v in (take.imu or {}).items()}
    np.savez_compressed(path, fps=take.fps, name=take.name, credit=credit, joint_names=np.array(JOINT_NAMES),
                        gt_pos=take.gt_pos.astype(np.float32), **take.signals.as_dict("sig_"), **imu)


def from_sample(path):
    try:
        d = np.load(path, allow_pickle=False)
        names = [str(n) for n in d["joint_names"]]
        if names != list(JOINT_NAMES):
            raise BvhError(f"{path}: sample was made for a different skeleton ({len(names)} joints)")
        imu = {k[4:]: d[k].astype(np.float64) for k in d.files if k.startswith("imu_")}
        return Take(str(d["name"]), Signals.from_dict(d, "sig_"), d["gt_pos"].astype(np.float64), float(d["fps"]), imu)
    except (OSError, KeyError, ValueError) as e:
        raise BvhError(f"{path}: not a readable edgepose sample file ({e})") from None


def find_clips(paths, split=None):
    """Expand files and folders into a list of BVH/sample files; folders with a MANIFEST.tsv filter by split."""
    out = []
    for p in map(Path, paths):
        if p.is_dir():
            manifest = p / "MANIFEST.tsv"
            if manifest.exists():
                import csv
                with open(manifest, newline="") as f:
                    rows = list(csv.DictReader(f, delimiter="\t"))
                out += [p / r["file"] for r in rows if split is None or r.get("split") == split]
            else:
                out += sorted(list(p.rglob("*.bvh")) + list(p.rglob("*.npz")))
        elif p.exists():
            out.append(p)
        else:
            raise FileNotFoundError(f"no such file or folder: {p}")
    return out


def load_take(path, **kw):
    return from_sample(path) if str(path).endswith(".npz") else from_bvh(path, **kw)
