"""Where a CPU training step's time goes, and training windows a minute for each recipe, in one run.

    python bench/train_step.py [--data ../shared/mocap] [--batch 128] [--best-of 16,8,4] [--threads 1,2]
                               [--steps 6] [--precision fp32,bf16] [--winner both|only|off]
                               [--json out/train_step.json]

For each (K, threads) it times the stages of the recipe's step (a copy of models.train.recipe_losses
with a clock between its parts) on the same batches: making the batch (motion.dataset.make_batch, one
numpy process), the prior-mean decode (z = 0), the K latent rollouts, the FK of both, the loss terms
and backward. Then the real step (models.train.RecipeStep and Adam), with every latent's gradient and
with --winner-grad's (recipe_losses_winner), as windows a minute (batch making runs in a process of
its own beside the step, so a step costs its slower half).
Numbers vary with what else runs on the machine: say so beside them.
"""
import argparse
import itertools
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np
import torch

from edge.imus import ImuNoise
from models import train as tr
from models.nets import CVAE, LATENT
from motion import dataset as ds
from motion.synth import DeviceNoise


def stage_times(model, b, K, eps=0.02):
    """One recipe step with a clock at each stage boundary -> {stage: seconds}."""
    x, gt = b["features"], b["gt_rel"]
    W, B = x.shape[:2]
    t = {}
    c = time.perf_counter()

    def lap(name):
        nonlocal c
        now = time.perf_counter()
        t[name] = t.get(name, 0.0) + now - c
        c = now

    rot0, con0, _ = model.decode(x, torch.zeros(W, B, LATENT))
    lap("decode z=0")
    if K:
        eps_z = torch.randn(1, B * K, LATENT).expand(W, -1, -1)
        rotk, _, _ = model.decode(x.repeat(1, K, 1), eps_z)
        lap(f"decode K={K}")
    pos0 = tr.head_positions(rot0, b["root_rot"])
    posk = tr.head_positions(rotk, b["root_rot"].repeat(1, K, 1, 1)) if K else None
    lap("FK")
    err0 = pos0 - gt
    loss = 1000 * (err0 ** 2).sum(-1).mean()
    if K:
        per_window = ((posk - gt.repeat(1, K, 1, 1)) ** 2).sum(-1).mean(dim=(0, 2)).view(K, B)
        loss = loss + 1000 * ((1 - eps) * per_window.min(0).values.mean() + eps * per_window.mean())
        loss = loss + 1000 * (tr.floor_depth(posk, b["anchor_y"].repeat(1, K)) ** 2).sum(-1).mean()
        loss = loss + 10000 * (tr.clearance(posk, gt.repeat(1, K, 1, 1)) ** 2).mean()
    loss = loss + 1000 * (tr.floor_depth(pos0, b["anchor_y"]) ** 2).sum(-1).mean()
    loss = loss + 10000 * (tr.clearance(pos0, gt) ** 2).mean()
    loss = loss + 0.1 * torch.nn.functional.binary_cross_entropy(con0.clamp(1e-6, 1 - 1e-6), b["contacts"])
    loss = loss + 0.1 * ((rot0 - b["rot6d"]) ** 2).mean()
    lap("loss terms")
    model.zero_grad()
    loss.backward()
    lap("backward")
    torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
    for p in (p for p in model.parameters() if p.grad is not None):   # an SGD update stands in for Adam
        p.data.add_(p.grad, alpha=-1e-9)
    lap("update")
    return t


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--window", type=int, default=60)
    ap.add_argument("--hidden", type=int, default=256)
    ap.add_argument("--best-of", default="16,8,4")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--precision", default="fp32", help="fp32, bf16 or both (fp32,bf16): --bf16's autocast")
    ap.add_argument("--winner", default="both", choices=("both", "only", "off"),
                    help="time the winner's-gradient step, the all-K one, or both")
    ap.add_argument("--json")
    a = ap.parse_args()
    cs = ds.build(a.data, "train")
    rng = np.random.default_rng(0)
    starts = ds.window_starts(cs, a.window)
    t0 = time.perf_counter()
    batches = [ds.make_batch(cs, rng.choice(starts, a.batch), a.window, rng, DeviceNoise(), ImuNoise())
               for _ in range(a.steps)]
    make_s = (time.perf_counter() - t0) / a.steps
    batches = [tr.to_t(b) for b in batches]
    torch.manual_seed(0)
    model = CVAE(hidden=a.hidden)
    model.norm.fit(batches[0]["features"])
    print(f"batch of {a.batch} windows made in {make_s:.3f} s (numpy, one process)")
    rows = []
    opt = torch.optim.Adam(model.parameters(), lr=1e-9)

    def real_step(step, b, bf16):
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            loss, _ = step(b)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()

    winners = {"both": (False, True), "only": (True,), "off": (False,)}[a.winner]
    for threads in map(int, a.threads.split(",")):
        torch.set_num_threads(threads)
        for K in map(int, a.best_of.split(",")):
            stage_times(model, batches[0], K)          # warm-up
            total = {}
            for b in batches:
                for k, v in stage_times(model, b, K).items():
                    total[k] = total.get(k, 0.0) + v / len(batches)
            print(f"threads {threads} K={K:2d} stages: " + ", ".join(f"{k} {v:.2f} s" for k, v in total.items()))
            for winner, precision in itertools.product(winners, a.precision.split(",")):
                step = tr.RecipeStep(model, K, 0.02, winner_grad=winner)
                bf16 = precision == "bf16"
                real_step(step, batches[0], bf16)            # warm-up
                t0 = time.perf_counter()
                for b in batches:
                    real_step(step, b, bf16)
                took = (time.perf_counter() - t0) / len(batches)
                wpm = a.batch / max(took, make_s) * 60
                rows.append({"threads": threads, "best_of": K, "winner_grad": winner, "precision": precision,
                             "step_s": took, "stages_s": total, "windows_per_minute": wpm})
                print(f"threads {threads} K={K:2d} {'winner-grad' if winner else 'all K grad '} {precision}: "
                      f"step {took:.2f} s -> {wpm:,.0f} windows a minute", flush=True)
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({"batch": a.batch, "make_batch_s": make_s, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
