"""Training windows a second: the numpy batch maker (one process, motion.dataset.make_batch, what
each of v0.4's batch-making processes ran) against models.batches on a torch device, measured in one
run, on the same split.

    python bench/batches.py [--data .cache/pack/edgepose-pack.npz] [--device cpu|cuda] [--batch 256] [--seconds 20]

On an accelerator the device's figure is what a training step gets without waiting for the CPUs; the
ratio says how many numpy processes it replaces.
"""
import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np
import torch

from edge.imus import ImuNoise
from motion import dataset as ds
from motion.synth import DeviceNoise
from models.batches import DeviceBatches


def rate(make, seconds, sync=lambda: None):
    make()                                   # warm-up (allocations, kernels)
    sync()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        n += make()
    sync()
    return n / (time.perf_counter() - t0)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=".cache/pack/edgepose-pack.npz")
    ap.add_argument("--split", default="train")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--window", type=int, default=60)
    ap.add_argument("--seconds", type=float, default=20)
    a = ap.parse_args()
    torch.set_num_threads(1)
    cs = ds.build(a.data, a.split)
    starts, rng = ds.window_starts(cs, a.window), np.random.default_rng(0)

    def numpy_batch():
        ds.make_batch(cs, rng.choice(starts, a.batch), a.window, rng, DeviceNoise(), ImuNoise())
        return a.batch

    dev = DeviceBatches(cs, a.window, a.device, seed=0)

    def device_batch():
        dev.next(a.batch)
        return a.batch

    sync = torch.cuda.synchronize if dev.device.type == "cuda" else (lambda: None)
    r_np = rate(numpy_batch, a.seconds)
    r_dev = rate(device_batch, a.seconds, sync)
    name = torch.cuda.get_device_name(dev.device) if dev.device.type == "cuda" else "CPU, 1 thread"
    print(f"{a.split}: {len(cs.names)} clips; batches of {a.batch} windows of {a.window} frames")
    print(f"numpy, one process:      {r_np * 60:12,.0f} windows a minute")
    print(f"models.batches on {dev.device} ({name}): {r_dev * 60:12,.0f} windows a minute  ({r_dev / r_np:.1f}x)")


if __name__ == "__main__":
    main()
