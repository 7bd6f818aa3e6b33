"""Train the pose autoencoder and the CVAE on the `train` split, select on `val`, export ONNX.

    python -m models.train --data ../shared/mocap [--sources cmu daz hdm05] [--minutes 100] [--device cuda]
    python -m models.train --data .cache/pack/edgepose-pack.npz ...   # the training pack (motion.pack)
    torchrun --nproc_per_node=2 -m models.train ...      # the same recipe on several GPUs (PyTorch DDP)
    scripts/train-device                                 # one fixed-budget run on an accelerator, from the pack

Seeded, with a progress bar and a log (models/train_log.txt). The decoder reads the 4-point features
and the seven extra IMUs (edge.features), trained on random sensor sets with drop-outs and IMU noise
(motion.dataset.random_imus, edge.imus.ImuNoise). The shipped recipe (recipe_losses, --best-of 8):
  L = w_pos * (MSE(FK positions at z=0) + relaxed best-of-K MSE) + w_floor * floor depth^2
      + w_clear * leg-clearance shortfall^2 + gamma * BCE(contacts) + w_rot * MSE(6D)
(v0.3, shipped: v0.2's run fine-tuned with --best-of 16 --eps 0.02 --clearance 10000 --lr 5e-4; see
models/MODEL_CARD.md.)
SSI eq. 1's CVAE loss (w_pos * MSE + lambda * KL + ...) is --best-of 0. Under torchrun each process
(one per GPU, or CPU processes with the gloo backend) draws its own batches; DDP averages the gradients,
and rank 0 validates, logs and saves.

Sample-diversity experiments measured before (models/MODEL_CARD.md, not shipped): --posterior (the
encoder also sees the pose) and --learned-prior (a conditional prior p(z | trackers, GRU state)).
"""
import argparse
import json
import multiprocessing as mp
import hashlib
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

from edge.progress import Progress
from edge.imus import ImuNoise
from edge.physics import INTERSECT_M, LEG_SEGMENTS
from motion.pack import read_clips
from motion.synth import DeviceNoise
from edge.skeleton import ANKLES, HEAD, LOWER_BODY, NUM_PREDICTED, TOES
from motion import dataset as ds
from motion.augment import Augment, window_span
from models.nets import CVAE, HIDDEN, LATENT, PoseAE, fk_positions, matrix_from_6d

LOSS = {"w_pos": 1000.0, "lambda_kl": 5.0, "gamma_bce": 0.1, "w_rot": 0.1, "w_floor": 1000.0, "w_clear": 0.0}


_TRAIN = None      # the train ClipSet, set before the producers fork so that they share it


def _producer(q, window, batch, seed, vigorous=0.0, windows_by="frames", cap_minutes=10.0, augment=None):
    torch.set_num_threads(1)
    cs = _TRAIN
    # a window read at up to `fastest` x needs that many more frames of its clip
    starts = ds.window_starts(cs, window_span(window, augment.fastest if augment else 1.0))
    draw = ds.WindowDraw(cs, starts, windows_by, cap_minutes)
    # --vigorous: that share of every batch from windows that lift a toe (kicks are rare in the data)
    lifted = ds.vigorous_starts(cs, starts, window) if vigorous > 0 else starts
    n_lifted = int(round(vigorous * batch))
    rng = np.random.default_rng(seed)
    noise, imu_noise = DeviceNoise(), ImuNoise()
    while True:
        picks = np.concatenate([draw.draw(rng, batch - n_lifted), rng.choice(lifted, n_lifted)])
        q.put(ds.make_batch(cs, picks, window, rng, noise, imu_noise, augment=augment))


def _sha256(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def cpu_state(model):
    """The weights as CPU tensors: a checkpoint made on an accelerator loads anywhere."""
    return {k: v.detach().cpu() for k, v in model.state_dict().items()}


def to_t(b, device="cpu"):
    return {k: torch.from_numpy(np.ascontiguousarray(v)).to(device) for k, v in b.items()}


def head_positions(rot6d, root_rot):
    """Decoder 6D output -> joint positions relative to the head (the runtime hangs the body from it).
    In fp32 under --bf16 too: bf16's 8-bit mantissa would put a foot a metre down the chain ~4 mm off."""
    with torch.autocast(rot6d.device.type, enabled=False):
        local = matrix_from_6d(rot6d.float().reshape(rot6d.shape[:-1] + (NUM_PREDICTED, 6)))
        pos = fk_positions(root_rot.float(), local)
        return pos - pos[..., HEAD:HEAD + 1, :]


FOOT_JOINTS = np.concatenate([ANKLES, TOES])


def floor_depth(rel, anchor_y):
    """How far the ankles and toes go below the floor [...,4] (m, 0 above it): head-anchored positions
    plus the tracked head joint's height are heights above the floor."""
    return torch.relu(-(rel[..., FOOT_JOINTS, 1] + anchor_y[..., None]))


def segment_distance(p0, p1, q0, q1):
    """Closest distance between segments p0-p1 and q0-q1 [...,3] -> [...]: edge.physics.segment_distance
    in torch, so the loss sees the same leg gap the eval counts."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, f = (d1 * d1).sum(-1), (d2 * d2).sum(-1), (d2 * r).sum(-1)
    c, b = (d1 * r).sum(-1), (d1 * d2).sum(-1)
    denom = a * e - b * b
    ok = denom > 1e-12
    s = torch.where(ok, ((b * f - c * e) / torch.where(ok, denom, torch.ones_like(denom))).clamp(0, 1),
                    torch.zeros_like(denom))
    t = (b * s + f) / e.clamp_min(1e-12)
    s = torch.where(t < 0, (-c / a.clamp_min(1e-12)).clamp(0, 1),
                    torch.where(t > 1, ((b - c) / a.clamp_min(1e-12)).clamp(0, 1), s))
    t = t.clamp(0, 1)
    return (p0 + d1 * s[..., None] - (q0 + d2 * t[..., None])).norm(dim=-1)


def leg_gap(pos):
    """The smallest distance between a left-leg and a right-leg segment [...] (edge.physics.leg_gap)."""
    L, R = pos[..., LEG_SEGMENTS[0], :], pos[..., LEG_SEGMENTS[1], :]
    d = segment_distance(L[..., :, None, 0, :], L[..., :, None, 1, :], R[..., None, :, 0, :], R[..., None, :, 1, :])
    return d.flatten(-2).min(-1).values


def clearance(pos, gt):
    """How much closer than the truth the legs come, where the truth keeps them apart (m, >= 0): the
    legs may cross where the performer crossed them, never more (SSI sec. 4.3 collision criterion)."""
    return torch.relu(leg_gap(gt).clamp(max=INTERSECT_M) - leg_gap(pos))


def recipe_losses(model, b, K, eps=0.05):
    """The shipped recipe's terms (SSI eq. 1 with best-of-K sampling, see the module docstring):
    the prior mean (z = 0, what N=1 runs) regresses the pose; of K latents held fixed over each
    window, the closest to the truth is pulled towards it with weight 1 - eps and every one with eps
    (relaxed multiple-choice learning, Rupprecht et al. 2017), so the samples spread over the poses
    the trackers leave open while none drifts into nonsense; and no foot of any sample may sink
    below the floor. Returns a dict of scalar tensors."""
    x, gt = b["features"], b["gt_rel"]
    W, B = x.shape[:2]
    rot0, con0, _ = model.decode(x, torch.zeros(W, B, LATENT, device=x.device))
    eps_z = torch.randn(1, B * K, LATENT, device=x.device).expand(W, -1, -1)
    rotk, _, _ = model.decode(x.repeat(1, K, 1), eps_z)
    pos0 = head_positions(rot0, b["root_rot"])
    posk = head_positions(rotk, b["root_rot"].repeat(1, K, 1, 1))
    err0 = pos0 - gt
    per_window = ((posk - gt.repeat(1, K, 1, 1)) ** 2).sum(-1).mean(dim=(0, 2)).view(K, B)
    variety = (1 - eps) * per_window.min(0).values.mean() + eps * per_window.mean()
    floor = (floor_depth(pos0, b["anchor_y"]) ** 2).sum(-1).mean() + \
            (floor_depth(posk, b["anchor_y"].repeat(1, K)) ** 2).sum(-1).mean()
    clear = (clearance(pos0, gt) ** 2).mean() + (clearance(posk, gt.repeat(1, K, 1, 1)) ** 2).mean()
    bce = torch.nn.functional.binary_cross_entropy(con0.clamp(1e-6, 1 - 1e-6), b["contacts"])
    rot = ((rot0 - b["rot6d"]) ** 2).mean()
    return {"mse": (err0 ** 2).sum(-1).mean(), "variety": variety, "floor": floor, "clear": clear, "bce": bce,
            "rot": rot, "mpjpe": err0.norm(dim=-1).mean()}


def recipe_losses_winner(model, b, K, eps=0.05):
    """recipe_losses with the same expected gradient in about half the time on a CPU: the K latent
    rollouts run without autograd, only to find each window's best; then the prior mean, the best and
    one latent drawn at random run again with it. The min over K has the best's gradient (which latent
    wins is piecewise constant), and the mean over K (the eps term, and the samples' floor and clearance
    terms) the random one's in expectation. Backward through K rollouts was two thirds of a step
    (bench/train_step.py). The terms it returns are the same quantities, the K-sample ones estimated."""
    x, gt = b["features"], b["gt_rel"]
    W, B = x.shape[:2]
    eps_z = torch.randn(1, B * K, LATENT, device=x.device).expand(W, -1, -1)
    with torch.no_grad():
        rotk, _, _ = model.decode(x.repeat(1, K, 1), eps_z)
        posk = head_positions(rotk, b["root_rot"].repeat(1, K, 1, 1))
        per_window = ((posk - gt.repeat(1, K, 1, 1)) ** 2).sum(-1).mean(dim=(0, 2)).view(K, B)
        best = per_window.argmin(0)                                      # [B]
        other = torch.randint(K, (B,), device=x.device)
        window = torch.arange(B, device=x.device)
        chosen = eps_z.view(W, K, B, LATENT)[:, torch.cat([best, other]), torch.cat([window, window])]
    z = torch.cat([torch.zeros(W, B, LATENT, device=x.device), chosen], dim=1)      # [W,3B,L]: 0, best, random
    rot, con, _ = model.decode(x.repeat(1, 3, 1), z)
    pos = head_positions(rot, b["root_rot"].repeat(1, 3, 1, 1))
    pos0, posb, posr = pos[:, :B], pos[:, B:2 * B], pos[:, 2 * B:]
    rot0, con0 = rot[:, :B], con[:, :B]
    err0 = pos0 - gt
    err_b = ((posb - gt) ** 2).sum(-1).mean(dim=(0, 2))
    err_r = ((posr - gt) ** 2).sum(-1).mean(dim=(0, 2))
    variety = (1 - eps) * err_b.mean() + eps * err_r.mean()
    floor = (floor_depth(pos0, b["anchor_y"]) ** 2).sum(-1).mean() + (floor_depth(posr, b["anchor_y"]) ** 2).sum(-1).mean()
    clear = (clearance(pos0, gt) ** 2).mean() + (clearance(posr, gt) ** 2).mean()
    bce = torch.nn.functional.binary_cross_entropy(con0.clamp(1e-6, 1 - 1e-6), b["contacts"])
    rot_err = ((rot0 - b["rot6d"]) ** 2).mean()
    return {"mse": (err0 ** 2).sum(-1).mean(), "variety": variety, "floor": floor, "clear": clear, "bce": bce,
            "rot": rot_err, "mpjpe": err0.norm(dim=-1).mean()}


def cvae_losses(model, b, sample=True):
    """Training uses the posterior sample; validation decodes at the prior mean (epsilon = 0), as N=1 runs."""
    prior = None
    if sample:
        rot6d, con, mu, logvar, prior = model(b["features"], True, b["gt_rel"])
    else:
        mu = logvar = torch.zeros(b["features"].shape[:-1] + (LATENT,), device=b["features"].device)
        rot6d, con, _ = model.decode_prior_mean(b["features"])
    local = matrix_from_6d(rot6d.reshape(rot6d.shape[:-1] + (NUM_PREDICTED, 6)))
    pos = fk_positions(b["root_rot"], local)
    pos = pos - pos[..., HEAD:HEAD + 1, :]
    err = pos - b["gt_rel"]
    mse = (err ** 2).sum(-1).mean()
    if prior is None:
        kl = (-0.5 * (1 + logvar - mu ** 2 - logvar.exp())).mean()
    else:                          # KL(q || p) between diagonal Gaussians, p the learned prior
        mu_p, logvar_p = prior
        kl = (0.5 * (logvar_p - logvar + (logvar.exp() + (mu - mu_p) ** 2) / logvar_p.exp() - 1)).mean()
    bce = torch.nn.functional.binary_cross_entropy(con.clamp(1e-6, 1 - 1e-6), b["contacts"])
    rot = ((rot6d - b["rot6d"]) ** 2).mean()
    mpjpe = err.norm(dim=-1).mean()
    return mse, kl, bce, rot, mpjpe


def train_ae(cs_train, cs_val, steps, seed, log):
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    ae = PoseAE()
    ae.norm.fit(torch.from_numpy(ds.pose_batch(cs_train, rng.integers(0, len(cs_train.root), 20000))["positions"]))
    opt = torch.optim.Adam(ae.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps, eta_min=1e-5)
    with Progress(steps, "autoencoder") as bar:
        for it in range(steps):
            b = to_t(ds.pose_batch(cs_train, rng.integers(0, len(cs_train.root), 1024)))
            loss = ae_error(ae, b).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            bar.update(postfix=f"err {ae_error(ae, b).mean().item() * 100:.2f} cm" if it % 50 == 0 else None)
    ae.eval()
    with torch.no_grad():
        vb = to_t(ds.pose_batch(cs_val, np.arange(len(cs_val.root))))
        lower = ae_error(ae, vb)[:, LOWER_BODY].mean(-1).numpy()
    threshold = float(np.percentile(lower, 99))
    log(f"autoencoder: val lower-body error mean {lower.mean() * 100:.2f} cm, p99 (threshold) {threshold * 100:.2f} cm")
    return ae, threshold


def ae_error(ae, b):
    """Per-joint reconstruction distance [B,J] (metres)."""
    rot6d = ae(b["positions"])
    local = matrix_from_6d(rot6d.reshape(-1, NUM_PREDICTED, 6))
    pos = fk_positions(b["root_rot"], local)
    inp = b["positions"].reshape(-1, pos.shape[1], 3)
    pos = pos + inp[:, :1]  # the pelvis stays where the input put it
    return (pos - inp).norm(dim=-1)


class RecipeStep(torch.nn.Module):
    """One training step's loss as a module, so DDP wraps it: forward(batch) -> (total loss, terms)."""

    def __init__(self, model, best_of, eps, winner_grad=False):
        super().__init__()
        self.model, self.best_of, self.eps = model, best_of, eps
        self.losses = recipe_losses_winner if winner_grad else recipe_losses

    def forward(self, b):
        if self.best_of:
            t = self.losses(self.model, b, self.best_of, self.eps)
            loss = LOSS["w_pos"] * (t["mse"] + t["variety"]) + LOSS["w_floor"] * t["floor"] \
                + LOSS["w_clear"] * t["clear"]
        else:
            mse, kl, bce, rot, mpjpe = cvae_losses(self.model, b)
            t = {"mse": mse, "kl": kl, "bce": bce, "rot": rot, "mpjpe": mpjpe}
            loss = LOSS["w_pos"] * mse + LOSS["lambda_kl"] * kl
        return loss + LOSS["gamma_bce"] * t["bce"] + LOSS["w_rot"] * t["rot"], t


def distributed():
    """(rank, world size, local rank) from torchrun's environment; (0, 1, 0) when run alone."""
    return int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1)), int(os.environ.get("LOCAL_RANK", 0))


def pick_device(name, local_rank):
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda":
        if not torch.cuda.is_available():
            raise SystemExit("--device cuda: no CUDA device here (torch.cuda.is_available() is False); use --device cpu")
        torch.cuda.set_device(local_rank)
        return torch.device("cuda", local_rank)
    return torch.device("cpu")


def val_batches(cs_val, windows, device="cpu"):
    """{"unseen none": [4 batches], "unseen imus": .., "seen none": .., "seen imus": ..}: fixed noisy
    windows of 4 s (seeded: every run and models.validate draw the same), with no extra IMUs and with
    random sets of them, for the people the model never saw and those it saw."""
    out = {}
    people = cs_val.people if cs_val.people is not None else np.full(len(cs_val.names), "seen")
    for who in ("unseen", "seen"):
        if not (people == who).any():
            continue
        part = cs_val.subset(people == who)
        vrng = np.random.default_rng(1234)
        vstarts = ds.window_starts(part, 240)
        for kind in ("none", "imus"):
            out[f"{who} {kind}"] = [
                to_t(ds.make_batch(part, vrng.choice(vstarts, windows), 240, vrng, DeviceNoise(),
                                   ImuNoise(), with_imus=kind == "imus"), device) for _ in range(4)]
    return out


def validate(model, batches):
    model.eval()
    with torch.no_grad():
        v = np.mean([cvae_losses(model, vb, sample=False)[4].item() for vb in batches]) * 100
    model.train()
    return v


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--sources", nargs="*", default=None, choices=ds.SOURCES,
                    help="train on these sources only (cmu daz = CMU terms only; hdm05 is CC BY-SA, bandai CC BY-NC)")
    ap.add_argument("--minutes", type=float, default=100.0, help="CVAE wall-clock budget")
    ap.add_argument("--steps", type=int, default=0, help="stop after this many CVAE steps instead (0: the budget)")
    ap.add_argument("--ae-steps", type=int, default=4000)
    ap.add_argument("--batch", type=int, default=128, help="windows per step (per process under torchrun)")
    ap.add_argument("--window", type=int, default=60)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--best-of", type=int, default=8, metavar="K",
                    help="relaxed best-of-K sampling (the shipped recipe); 0 = SSI eq. 1's CVAE loss")
    ap.add_argument("--winner-grad", action="store_true",
                    help="backward through the prior mean, the best of the K latents and one at random only "
                         "(recipe_losses_winner: the same expected gradient, about half the CPU time)")
    ap.add_argument("--eps", type=float, default=0.05, help="weight of the mean over the K samples")
    ap.add_argument("--floor", type=float, default=LOSS["w_floor"], help="weight of the floor term (m^2)")
    ap.add_argument("--clearance", type=float, default=LOSS["w_clear"],
                    help="weight of the leg-clearance term (m^2): legs no closer than the truth's, up to 10 cm")
    ap.add_argument("--vigorous", type=float, default=0.0,
                    help="share of each batch drawn from windows that lift a toe 35 cm or more (kicks, jumps)")
    ap.add_argument("--windows-by", choices=ds.PERSON_RULES, default="frames",
                    help="how windows are drawn: uniformly over frames, or by person, each person's share the "
                         "same (people), the square root of their minutes (sqrt) or their minutes capped (capped)")
    ap.add_argument("--cap-minutes", type=float, default=10.0, help="a person's minutes counted at most (capped)")
    ap.add_argument("--mirror", type=float, default=0.0,
                    help="probability that a window is the left/right mirror image of its motion (motion.augment)")
    ap.add_argument("--tempo", default="1,1", metavar="SLOWEST,FASTEST",
                    help="windows read at a tempo drawn from this range, e.g. 0.8,1.25 (1,1: as recorded)")
    ap.add_argument("--source-conventions", action="store_true",
                    help="train on clips with each source's skeleton conventions left in (motion.neutrals; the "
                         "side-by-side run for taking them out); val is read as always")
    ap.add_argument("--posterior", action="store_true", help="encoder also sees the target pose (q(z|x,y))")
    ap.add_argument("--learned-prior", action="store_true",
                    help="conditional prior p(z | trackers, GRU state); implies --posterior")
    ap.add_argument("--kl", type=float, default=LOSS["lambda_kl"], help="KL weight lambda (--best-of 0)")
    ap.add_argument("--init", help="start the CVAE from this checkpoint folder (e.g. models/checkpoints) and "
                                   "reuse its autoencoder instead of training one")
    ap.add_argument("--resume", help="continue a run from its folder (--ckpt of that run): its last weights, "
                                     "optimizer state and autoencoder; the learning-rate schedule starts again")
    ap.add_argument("--ae-from", help="take the autoencoder and its threshold from this checkpoint folder "
                                      "(e.g. models/checkpoints) instead of training one")
    ap.add_argument("--hidden", type=int, default=HIDDEN, help="GRU width of the CVAE (v0.3: 128)")
    ap.add_argument("--batches", choices=("auto", "workers", "device"), default="auto",
                    help="where training windows are made: numpy processes (workers, the reference) or on the "
                         "training device itself (models.batches); auto: device on an accelerator")
    ap.add_argument("--workers", type=int, default=1, help="batch-making processes (numpy, one core each)")
    ap.add_argument("--reuse", type=int, default=1,
                    help="a batch may serve up to this many steps (each with fresh latents) when the next is not "
                         "ready yet: an accelerator need not wait for the CPUs")
    ap.add_argument("--bf16", action="store_true",
                    help="the forward pass under bfloat16 autocast (weights, Adam and the loss's sums stay fp32): "
                         "for a CPU with AVX-512 BF16 or AMX, or a GPU; see bench/train_step.py --precision")
    ap.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    ap.add_argument("--threads", type=int, default=0,
                    help="torch threads of the main process (0: 2 on an accelerator, else the cores per process)")
    ap.add_argument("--val-every", type=int, default=400)
    ap.add_argument("--val-windows", type=int, default=128, help="windows in each of the 4 validation batches of a kind")
    ap.add_argument("--out", default="models")
    ap.add_argument("--ckpt", default=".cache/train")
    ap.add_argument("--no-export", action="store_true", help="stop after saving the checkpoint")
    a = ap.parse_args(argv)
    a.posterior = a.posterior or a.learned_prior
    try:
        slowest, fastest = (float(x) for x in a.tempo.split(","))
    except ValueError:
        ap.error(f"--tempo {a.tempo!r}: two speeds, e.g. 0.8,1.25")
    if not 0.25 <= slowest <= fastest <= 4:
        ap.error(f"--tempo {a.tempo!r}: 0.25 <= slowest <= fastest <= 4")
    if not 0 <= a.mirror <= 1:
        ap.error(f"--mirror {a.mirror}: a probability in [0, 1]")
    a.augment = Augment(a.mirror, slowest, fastest) if a.mirror > 0 or (slowest, fastest) != (1, 1) else None
    return a


def main(argv=None):
    trainer = Trainer(parse_args(argv))
    trainer.load_data()
    trainer.start_batch_makers()
    trainer.autoencoder()
    trainer.build_model()
    trainer.fit()
    trainer.finish()


class Trainer:
    """One training run (rank `rank` of `world` under torchrun): its data, batch makers, models and
    checkpoints, in main's order."""

    def __init__(self, a):
        self.a = a
        self.rank, self.world, local_rank = distributed()
        self.device = device = pick_device(a.device, local_rank)
        self.lead = self.rank == 0
        self.out, self.ckpt = Path(a.out), Path(a.ckpt)
        if self.lead:
            self.ckpt.mkdir(parents=True, exist_ok=True)
            self.out.mkdir(parents=True, exist_ok=True)
        self.logf = open(self.out / "train_log.txt", "w") if self.lead else None
        torch.manual_seed(a.seed)
        # on an accelerator the main process only feeds it: leave the cores to the batch makers
        torch.set_num_threads(a.threads or (2 if device.type == "cuda" else max(1, (os.cpu_count() or 2) // self.world)))
        if device.type == "cuda":
            torch.backends.cuda.matmul.allow_tf32 = True
            torch.backends.cudnn.allow_tf32 = True
        LOSS["lambda_kl"], LOSS["w_floor"], LOSS["w_clear"] = a.kl, a.floor, a.clearance
        self.log(f"args: {vars(a)}  loss: {LOSS}  device: {device}  processes: {self.world}")
        self.t0 = self.t1 = time.time()
        self.best, self.best_it, self.it, self.done_before = float("inf"), -1, 0, 0
        self.data_sha256 = _sha256(a.data) if Path(a.data).is_file() else None

    def log(self, msg):
        if self.lead:
            print(msg, flush=True)
            self.logf.write(msg + "\n")
            self.logf.flush()

    def load_data(self):
        a = self.a
        self.cs_train = read_clips(a.data, "train", a.sources, conventions=not a.source_conventions)
        self.cs_val = read_clips(a.data, "val", a.sources)
        self.log(f"train: {len(self.cs_train.names)} clips, {len(self.cs_train.root) / 3600:.1f} min; val: "
                 f"{len(self.cs_val.names)} clips, {len(self.cs_val.root) / 3600:.1f} min (60 Hz)")

    def start_batch_makers(self):
        """The training windows' makers: the split on the device (models.batches), or forked numpy
        processes filling a queue; then the process group."""
        global _TRAIN
        a, rank = self.a, self.rank
        self.on_device = a.batches == "device" or (a.batches == "auto" and self.device.type == "cuda")
        self.q, self.procs = None, []
        seed = a.seed + 1 + 1000 * rank
        if self.lead:
            starts = ds.window_starts(self.cs_train, window_span(a.window, a.augment.fastest if a.augment else 1.0))
            for line in ds.WindowDraw(self.cs_train, starts, a.windows_by, a.cap_minutes).table():
                self.log(line)
        if self.on_device:
            from models.batches import DeviceBatches
            self.batches = DeviceBatches(self.cs_train, a.window, self.device, seed=seed, vigorous=a.vigorous,
                                         windows_by=a.windows_by, cap_minutes=a.cap_minutes, augment=a.augment)
            self.log(f"batches: made on {self.device} (models.batches), {len(self.batches.starts):,} window starts")
        else:
            _TRAIN = self.cs_train
            ctx = mp.get_context("fork")
            self.q = ctx.Queue(maxsize=max(8, 2 * a.workers))
            self.procs = [ctx.Process(target=_producer, args=(self.q, a.window, a.batch, seed + 100_000 * w,
                                                              a.vigorous, a.windows_by, a.cap_minutes, a.augment),
                                      daemon=True) for w in range(a.workers)]
            for p in self.procs:
                p.start()
            self.log(f"batches: made by {a.workers} numpy process(es)")
        if self.world > 1:       # after the fork: the batch producer must not inherit the process group's threads
            import torch.distributed as dist
            dist.init_process_group("nccl" if self.device.type == "cuda" else "gloo")

    def next_batch(self):
        """The next training batch, as tensors on the device."""
        if self.on_device:
            return self.batches.next(self.a.batch)
        return to_t(self.q.get(), self.device)

    def autoencoder(self):
        """The plausibility autoencoder and its threshold: trained here, or taken from a checkpoint folder;
        then the validation batches."""
        a, ckpt = self.a, self.ckpt
        self.t0 = time.time()
        ae_from = a.ae_from or a.resume or a.init
        if ae_from:
            import shutil
            if self.lead and Path(ae_from).resolve() != ckpt.resolve():
                shutil.copy(Path(ae_from) / "ae.pt", ckpt / "ae.pt")
            self.threshold = json.loads((Path(ae_from) / "meta.json").read_text())["plausibility_threshold_m"]
            self.log(f"autoencoder and threshold from {ae_from}")
        elif self.lead:
            ae, self.threshold = train_ae(self.cs_train, self.cs_val, a.ae_steps, a.seed, self.log)
            torch.save(ae.state_dict(), ckpt / "ae.pt")
            self.log(f"autoencoder trained in {time.time() - self.t0:.0f} s")
        if self.world > 1:
            import torch.distributed as dist
            dist.barrier()
        # Validation (rank 0): fixed noisy windows of 4 s, latent at the prior mean (what N=1 runs), with
        # no extra IMUs (the 4-point case) and with random sets of them, for the people the model never
        # saw (val subjects with no clip in train) and those it saw; selection on the unseen people's mean.
        self.val_batches = val_batches(self.cs_val, a.val_windows, self.device) if self.lead else {}
        if self.lead:
            self.choose_on = [k for k in self.val_batches if k.startswith("unseen")] or list(self.val_batches)
            self.log(f"validation: {', '.join(self.val_batches)}; chosen on {' + '.join(self.choose_on)}")

    def build_model(self):
        """The CVAE (new, from --init or --resume), its normalisers, the recipe step and the optimizer."""
        a, device = self.a, self.device
        model = self.model = CVAE(posterior=a.posterior, learned_prior=a.learned_prior, hidden=a.hidden)
        start_from = Path(a.resume) / "cvae_last.pt" if a.resume else Path(a.init) / "cvae.pt" if a.init else None
        if start_from:
            state = torch.load(start_from, weights_only=True, map_location="cpu")
            width = state["dec_gru.weight_hh_l0"].shape[1]
            if width != a.hidden:
                raise SystemExit(f"{start_from} is a --hidden {width} model; pass --hidden {width}")
            model.load_state_dict(state)
        fit = [{k: v.cpu() for k, v in self.next_batch().items()} for _ in range(8)]
        if not start_from:
            model.norm.fit(torch.cat([b["features"] for b in fit]))
        if a.posterior:
            model.target_norm.fit(torch.cat([b["gt_rel"].flatten(-2) for b in fit]))
        model.to(device)
        self.step = RecipeStep(model, a.best_of, a.eps, a.winner_grad)
        if self.world > 1:      # DDP broadcasts rank 0's weights and buffers now and averages the gradients
            self.step = torch.nn.parallel.DistributedDataParallel(self.step, find_unused_parameters=True)
            torch.save({k: v.cpu() for k, v in model.state_dict().items()}, self.ckpt / f"initial_rank{self.rank}.pt")
        self.opt = torch.optim.Adam(model.parameters(), lr=a.lr)
        if a.resume:
            resumed = torch.load(Path(a.resume) / "train_state.pt", weights_only=True, map_location=device)
            self.opt.load_state_dict(resumed["optimizer"])
            self.done_before = int(resumed["iterations"])
            self.log(f"resumed from {a.resume} after {self.done_before} steps")

    def _done(self):
        a = self.a
        done = self.it >= a.steps if a.steps else time.time() - self.t1 >= a.minutes * 60
        if self.world > 1:      # rank 0's clock decides for everyone, so every process runs the same steps
            import torch.distributed as dist
            stop = torch.full((1,), float(done))
            dist.broadcast(stop, 0)
            done = bool(stop.item())
        return done

    def fit(self):
        """Adam steps on the recipe's loss with a cosine learning rate, until the step count or the
        wall-clock budget; validation and checkpoints every --val-every steps and at the end."""
        a, opt, model = self.a, self.opt, self.model
        budget = a.minutes * 60
        self.t1 = time.time()
        bar = Progress(a.steps or int(budget), "cvae (steps)" if a.steps else "cvae (s)") if self.lead else None
        b, uses, self.waited = None, a.reuse, 0.0
        if self.lead and (a.init or a.resume):      # where the learning curve starts: the weights as loaded
            self._validate_and_save({})
        while not self._done():
            frac = self.it / a.steps if a.steps else (time.time() - self.t1) / budget
            for g in opt.param_groups:
                g["lr"] = float(1e-5 + 0.5 * (a.lr - 1e-5) * (1 + np.cos(np.pi * min(frac, 1.0))))  # a float: weights_only loads
            t_wait = time.time()
            if uses >= a.reuse or self.on_device or not self.q.empty():
                b, uses = self.next_batch(), 0
            uses += 1
            self.waited += time.time() - t_wait
            model.train()
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=a.bf16):
                loss, t = self.step(b)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            self.it += 1
            it = self.it
            if self.lead and it % 20 == 0:
                bar.n = it - 1 if a.steps else int(time.time() - self.t1) - 1
                bar.update(postfix=f"it {it} train {t['mpjpe'].item() * 100:.2f} cm bce {t['bce'].item():.3f}"
                                   + (f" floor {t['floor'].item() * 1e4:.2f} cm2" if "floor" in t else ""))
            last = (it >= a.steps) if a.steps else (time.time() - self.t1 >= budget)
            if self.lead and (it % a.val_every == 0 or last):
                self._validate_and_save(t)
        if bar:
            bar.close()

    def _validate_and_save(self, t):
        it, ckpt, model = self.it, self.ckpt, self.model
        v = {k: validate(model, vb) for k, vb in self.val_batches.items()}
        score = float(np.mean([v[k] for k in self.choose_on]))
        self.log(f"it {it} t {time.time() - self.t1:.0f}s (data wait {self.waited:.0f}s) lr "
                 f"{self.opt.param_groups[0]['lr']:.2e} train mpjpe {t['mpjpe'].item() * 100 if t else float('nan'):.2f} "
                 + " ".join(f"{k} {x.item():.4f}" for k, x in t.items() if k != "mpjpe")
                 + " | val mpjpe (head-anchored, no IK) " + " ".join(f"{k} {x:.2f}" for k, x in v.items()) + " cm")
        if score < self.best:
            self.best, self.best_it = score, it
            torch.save(cpu_state(model), ckpt / "cvae.pt")
        # where a later run continues from (--resume), whatever val said
        torch.save(cpu_state(model), ckpt / "cvae_last.pt")
        torch.save({"optimizer": self.opt.state_dict(), "iterations": self.done_before + it}, ckpt / "train_state.pt")
        self.write_meta()

    def write_meta(self):
        a, device, sources = self.a, self.device, self.a.sources or sorted(ds.SOURCE_FOLDERS)
        meta = {"plausibility_threshold_m": self.threshold, "iterations": self.done_before + self.it,
                "run_iterations": self.it, "hidden": a.hidden, "resumed_from": a.resume,
                "wall_clock_s": time.time() - self.t1,
                "windows_per_minute": self.it * a.batch / max(time.time() - self.t1, 1e-9) * 60,
                "batches_on": "device" if getattr(self, "on_device", False) else "workers",
                "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor(),
                "data": a.data, "data_sha256": self.data_sha256, "best_iteration": self.best_it,
                "val_mpjpe_cm_training": self.best, "minutes": a.minutes, "sources": sources,
                "licences": ds.source_licences(sources),
                "loss": LOSS, "best_of": a.best_of, "winner_grad": a.winner_grad, "eps": a.eps, "vigorous": a.vigorous, "posterior_encoder": a.posterior,
                "learned_prior": a.learned_prior, "init": a.init, "batch": a.batch, "window": a.window, "lr": a.lr,
                "seed": a.seed, "bf16": a.bf16, "windows_by": a.windows_by, "cap_minutes": a.cap_minutes, "mirror": a.mirror,
                "tempo": a.tempo, "processes": self.world, "device": str(device), "train_clips": len(self.cs_train.names),
                "train_minutes": len(self.cs_train.root) / 3600, "features": "4-point + 7 IMUs (edge.features)"}
        (self.ckpt / "meta.json").write_text(json.dumps(meta, indent=2))

    def finish(self):
        for p in self.procs:
            p.terminate()
        if self.world > 1:      # every process ends with the same weights: rank r saves its own copy to show it
            import torch.distributed as dist
            torch.save({k: v.cpu() for k, v in self.model.state_dict().items()}, self.ckpt / f"final_rank{self.rank}.pt")
            dist.barrier()
            dist.destroy_process_group()
        if not self.lead:
            return
        took = time.time() - self.t1
        self.log(f"cvae: {self.it} iterations in {took:.0f} s ({self.it * self.a.batch / max(took, 1e-9) * 60:,.0f} "
                 f"windows a minute, {self.waited / max(took, 1e-9):.0%} of the time making or waiting for batches); "
                 f"best val {self.best:.2f} cm at it {self.best_it}")
        self.write_meta()
        if self.a.no_export:
            return
        from models.export import export_all
        export_all(self.ckpt, self.out)
        self.log("exported ONNX models and manifest")


if __name__ == "__main__":
    main()
