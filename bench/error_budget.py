"""Where the error of each extra-IMU set sits, on the validation split (the variable-sensor-set issue).

    python bench/error_budget.py --data ../shared/mocap [--models DIR] [--out out/error_budget]

For no extra IMUs, both shins, thighs and shins, and all seven, at N=1 (int8 by default), it runs
edge eval and splits the error it finds:
- the pelvis's place (horizontal and vertical), and how much of the horizontal error is slow (what a
  1 s moving average of it keeps: a lean held for seconds, not jitter);
- the pose about the pelvis: mpjpe once each frame's pelvis is moved onto the truth's (what a perfect
  pelvis would leave);
- what the synthesised IMU noise costs: the same eval with noise-free IMUs, and with the mounting
  error alone (edge.imus.ImuNoise's terms);
- the thigh and shin direction errors, in degrees, after the leg IK.
Prints one table with each figure against the `none` row's mpjpe and writes it as JSON. About
three minutes on 2 cores.
"""
import argparse
import json
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from edge.options import PipelineOptions
from motion.evaluate import evaluate
from edge.imus import ImuNoise, parse_set
from edge.inference import DEFAULT_PRECISION
from edge.skeleton import JOINT

SETS = {"none": "none", "shins": "l_shin,r_shin", "thighs+shins": "l_thigh,r_thigh,l_shin,r_shin", "all seven": "all"}
NOISE = {"noise_free": ImuNoise(0.0, 0.0, 0.0, 0.0), "mounting_only": ImuNoise(ImuNoise.mount_max_deg, 0.0, 0.0, 0.0)}
SLOW_S = 1.0


def direction_error_deg(pred, gt, a, b):
    """Per frame, the angle between the predicted and true directions from joint a to joint b, degrees."""
    def unit(x):
        v = x[:, b] - x[:, a]
        return v / np.linalg.norm(v, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip((unit(pred) * unit(gt)).sum(-1), -1.0, 1.0)))


def moving_average(x, k):
    """Centred moving average of x [T,D] over k frames (k no longer than T)."""
    kernel = np.ones(k) / k
    return np.stack([np.convolve(x[:, i], kernel, mode="same") for i in range(x.shape[1])], axis=1)


def split_errors(dump):
    """The error budget of one eval from its --dump folder."""
    err, pelvis_h, pelvis_v, rel, slow, thigh, shin = [], [], [], [], [], [], []
    for f in sorted(Path(dump).glob("*.npz")):
        z = np.load(f)
        w = int(z["warmup_frames"])
        pred, gt = z["pred_pos"][w:].astype(np.float64), z["gt_pos"][w:].astype(np.float64)
        off = pred[:, :1] - gt[:, :1]                   # the pelvis's error, carried by every joint
        err.append(np.linalg.norm(pred - gt, axis=-1).mean(-1))
        rel.append(np.linalg.norm(pred - off - gt, axis=-1).mean(-1))
        h = off[:, 0, [0, 2]]
        pelvis_h.append(np.linalg.norm(h, axis=-1))
        pelvis_v.append(np.abs(off[:, 0, 1]))
        slow.append(np.linalg.norm(moving_average(h, min(int(SLOW_S * z["fps"]), len(h))), axis=-1))
        for side in "lr":
            hip, knee, ankle = JOINT[side + "_hip"], JOINT[side + "_knee"], JOINT[side + "_ankle"]
            thigh.append(direction_error_deg(pred, gt, hip, knee))
            shin.append(direction_error_deg(pred, gt, knee, ankle))
    mean = lambda parts: float(np.concatenate(parts).mean())
    cm = lambda parts: mean(parts) * 100
    return {"mpjpe_cm": cm(err), "pelvis_horizontal_cm": cm(pelvis_h), "pelvis_vertical_cm": cm(pelvis_v),
            "pelvis_horizontal_slow_cm": cm(slow), "mpjpe_perfect_pelvis_cm": cm(rel),
            "thigh_deg": mean(thigh), "shin_deg": mean(shin)}


def _run(job):
    """One eval: with the default IMU noise (label None) its error budget, else its mpjpe alone."""
    name, label, kwargs = job
    with tempfile.TemporaryDirectory() as dump:
        r = evaluate([kwargs.pop("data")], kwargs.pop("options"), split="val", log=lambda *a: None, dump=dump if label is None else None,
                     imu_noise=NOISE.get(label), **kwargs)
        return name, label, split_errors(dump) if label is None else r["mpjpe_cm"]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--models", help="the model folder to measure (default: the shipped models/)")
    ap.add_argument("--precision", choices=("fp32", "int8"), default=DEFAULT_PRECISION)
    ap.add_argument("--out", default="out/error_budget")
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args()
    jobs = []
    for name, spec in SETS.items():
        kwargs = {"data": a.data, "options": PipelineOptions(precision=a.precision), "models": a.models, "trackers": parse_set(spec)}
        jobs += [(name, label, dict(kwargs)) for label in [None, *(NOISE if spec != "none" else ())]]
    table = {name: {} for name in SETS}
    with ProcessPoolExecutor(a.jobs) as ex:
        for name, label, r in ex.map(_run, jobs):
            if label is None:
                table[name].update(r)
            else:
                table[name][f"mpjpe_{label}_cm"] = r
    none = table["none"]["mpjpe_cm"]
    cols = [("mpjpe_cm", "mpjpe"), ("mpjpe_perfect_pelvis_cm", "perfect pelvis"),
            ("mpjpe_noise_free_cm", "noise-free IMUs"), ("mpjpe_mounting_only_cm", "mounting only")]
    print(f"val, N=1 {a.precision}; each mpjpe in cm and against the `none` row's {none:.3f} cm")
    print(f"{'set':<14}" + "".join(f"{title:>22}" for _, title in cols)
          + f"{'pelvis h (slow) / v':>24}{'thigh / shin deg':>18}")
    for name, row in table.items():
        cells = "".join(f"{row[k]:>12.3f} ({row[k] / none:.3f}x)" if k in row else f"{'':>22}" for k, _ in cols)
        print(f"{name:<14}{cells}{row['pelvis_horizontal_cm']:>9.2f} ({row['pelvis_horizontal_slow_cm']:.2f}) / "
              f"{row['pelvis_vertical_cm']:.2f}{row['thigh_deg']:>10.1f} / {row['shin_deg']:.1f}")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "error_budget.json").write_text(json.dumps({"precision": a.precision, "models": a.models or "models/",
                                                       "slow_window_s": SLOW_S, "sets": table}, indent=2) + "\n")


if __name__ == "__main__":
    main()
