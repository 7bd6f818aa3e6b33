"""Make the bundled sample take: tracker signals plus ground-truth joint positions from one CMU clip (no BVH).

    python -m edgetools.make_sample --clip ../shared/mocap/cmu_amc2bvh/09/09_12.bvh --out samples/cmu_09_12_walk.npz
"""
import argparse
from pathlib import Path

from motion.takes import from_bvh, save_sample

CMU_CREDIT = ("The data used in this project was obtained from mocap.cs.cmu.edu. "
              "The database was created with funding from NSF EIA-0196217.")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clip", default="../shared/mocap/cmu_amc2bvh/09/09_12.bvh")
    ap.add_argument("--out", default="samples/cmu_09_12_walk.npz")
    ap.add_argument("--session", default="samples/cmu_09_12_walk.session.npz",
                    help="also write the device recording the demo replays (all three transports)")
    a = ap.parse_args()
    take = from_bvh(a.clip)
    take.name = "CMU " + Path(a.clip).stem
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    save_sample(a.out, take, CMU_CREDIT)
    print(f"wrote {a.out}: {take.frames} frames, {Path(a.out).stat().st_size / 1024:.0f} KiB")
    if a.session:
        from edgetools.sim.session import synthesize
        session = synthesize(take, ("serial", "i2c", "can"), seed=0)
        session.meta["credit"] = CMU_CREDIT
        session.save(a.session)
        print(f"wrote {a.session}: {session.duration:.1f} s of serial, I2C and CAN traffic, "
              f"{Path(a.session).stat().st_size / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
