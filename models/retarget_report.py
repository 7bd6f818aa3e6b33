"""Report how closely retargeting follows each source: mean angle between canonical and source bones.

    python -m models.retarget_report --data ../shared/mocap
"""
import argparse
from collections import defaultdict

import numpy as np

from motion import bvh
from edge.progress import Progress
from motion.retarget import LIMB_BONES, detect_source, direction_errors_deg, retarget
from edge.skeleton import JOINT_NAMES
from motion.dataset import clip_paths


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    a = ap.parse_args()
    per_source = defaultdict(list)
    paths = clip_paths(a.data)
    with Progress(len(paths), "retarget") as bar:
        for p in paths:
            clip = bvh.load(p)
            motion, src = retarget(clip)
            per_source[detect_source(clip)].append(direction_errors_deg(motion, src).mean(0))
            bar.update()
    print(f"{'source':8} {'clips':>5} {'limbs (deg)':>12} {'all bones':>10}   worst bone")
    for source, errs in sorted(per_source.items()):
        e = np.mean(errs, axis=0)
        worst = int(np.argmax(e))
        print(f"{source:8} {len(errs):>5} {e[LIMB_BONES].mean():>12.3f} {e.mean():>10.2f}   "
              f"{JOINT_NAMES[worst + 1]} {e[worst]:.1f}")
    print("limbs: upper arms, forearms, thighs, shins, feet; the fixed pelvis and shoulder-girdle bones take the "
          "canonical proportions, so they differ from the source by the proportion mismatch.")


if __name__ == "__main__":
    main()
