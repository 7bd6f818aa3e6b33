"""Train the pose autoencoder and the CVAE on the `train` split, select on `val`, export ONNX.

    python -m models.train --data ../shared/mocap [--sources cmu daz] [--minutes 40]

Seeded, CPU only, with a progress bar and a log (models/train_log.txt). Loss (SSI eq. 1):
  L = w_pos * MSE(FK positions, head-anchored, m^2) + lambda * KL + gamma * BCE(contacts) + w_rot * MSE(6D)

Sample-diversity experiments (measured in models/MODEL_CARD.md, none shipped): --posterior (the
encoder also sees the pose), --learned-prior (a conditional prior p(z | trackers, GRU state)), and
--variety K --init models/checkpoints (best-of-K fine-tuning of the shipped decoder).
"""
import argparse
import json
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np
import torch

from edge.progress import Progress
from edge.signals import DeviceNoise
from edge.skeleton import HEAD, LOWER_BODY, NUM_PREDICTED
from models import dataset as ds
from models.nets import CVAE, LATENT, PoseAE, fk_positions, matrix_from_6d

LOSS = {"w_pos": 1000.0, "lambda_kl": 5.0, "gamma_bce": 0.1, "w_rot": 0.1}


def _producer(q, root, sources, window, batch, seed):
    torch.set_num_threads(1)
    cs = ds.build(root, "train", sources)
    starts = ds.window_starts(cs, window)
    rng = np.random.default_rng(seed)
    noise = DeviceNoise()
    while True:
        q.put(ds.make_batch(cs, rng.choice(starts, batch), window, rng, noise))


def to_t(b):
    return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in b.items()}


def head_positions(rot6d, root_rot):
    """Decoder 6D output -> joint positions relative to the head (the runtime hangs the body from it)."""
    local = matrix_from_6d(rot6d.reshape(rot6d.shape[:-1] + (NUM_PREDICTED, 6)))
    pos = fk_positions(root_rot, local)
    return pos - pos[..., HEAD:HEAD + 1, :]


def variety_losses(model, b, K):
    """Best-of-K ("variety", multiple-choice) training for sample diversity: the prior mean (z = 0, what
    N=1 runs) learns the usual regression, and of K latents held fixed over the window, only the one
    closest to the truth is pulled towards it, so the samples spread over the poses the trackers leave
    open instead of collapsing onto the mean. Returns (mse at z=0, best-of-K mse, bce, rot, mpjpe at z=0)."""
    x, gt = b["features"], b["gt_rel"]
    W, B = x.shape[:2]
    rot0, con0, _ = model.decode(x, torch.zeros(W, B, LATENT))
    eps = torch.randn(1, B * K, LATENT).expand(W, -1, -1)
    rotk, _, _ = model.decode(x.repeat(1, K, 1), eps)
    err0 = head_positions(rot0, b["root_rot"]) - gt
    errk = head_positions(rotk, b["root_rot"].repeat(1, K, 1, 1)) - gt.repeat(1, K, 1, 1)
    per_window = (errk ** 2).sum(-1).mean(dim=(0, 2)).view(K, B)
    best = per_window.min(0).values.mean()
    bce = torch.nn.functional.binary_cross_entropy(con0.clamp(1e-6, 1 - 1e-6), b["contacts"])
    rot = ((rot0 - b["rot6d"]) ** 2).mean()
    return (err0 ** 2).sum(-1).mean(), best, bce, rot, err0.norm(dim=-1).mean()


def cvae_losses(model, b, sample=True):
    """Training uses the posterior sample; validation decodes at the prior mean (epsilon = 0), as N=1 runs."""
    prior = None
    if sample:
        rot6d, con, mu, logvar, prior = model(b["features"], True, b["gt_rel"])
    else:
        mu = logvar = torch.zeros(b["features"].shape[:-1] + (LATENT,))
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


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--sources", nargs="*", default=None, choices=sorted(ds.SOURCE_FOLDERS),
                    help="train on these sources only (cmu daz = CMU only, commercial-safe)")
    ap.add_argument("--minutes", type=float, default=45.0, help="CVAE wall-clock budget")
    ap.add_argument("--ae-steps", type=int, default=4000)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--window", type=int, default=60)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--posterior", action="store_true", help="encoder also sees the target pose (q(z|x,y))")
    ap.add_argument("--learned-prior", action="store_true",
                    help="conditional prior p(z | trackers, GRU state); implies --posterior")
    ap.add_argument("--kl", type=float, default=LOSS["lambda_kl"], help="KL weight lambda")
    ap.add_argument("--variety", type=int, default=0, metavar="K",
                    help="best-of-K training for sample diversity (z = 0 regression + the best of K latents)")
    ap.add_argument("--init", help="start the CVAE from this checkpoint folder (e.g. models/checkpoints) and "
                                   "reuse its autoencoder instead of training one")
    ap.add_argument("--out", default="models")
    ap.add_argument("--ckpt", default=".cache/train")
    a = ap.parse_args()

    out, ckpt = Path(a.out), Path(a.ckpt)
    ckpt.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    logf = open(out / "train_log.txt", "w")

    def log(msg):
        print(msg, flush=True)
        logf.write(msg + "\n")
        logf.flush()

    torch.manual_seed(a.seed)
    torch.set_num_threads(2)
    LOSS["lambda_kl"] = a.kl
    log(f"args: {vars(a)}  loss: {LOSS}")
    cs_train = ds.build(a.data, "train", a.sources)
    cs_val = ds.build(a.data, "val", a.sources)
    log(f"train: {len(cs_train.names)} clips, {len(cs_train.root) / 3600:.1f} min; val: {len(cs_val.names)} clips, "
        f"{len(cs_val.root) / 3600:.1f} min (60 Hz)")

    q = mp.get_context("fork").Queue(maxsize=8)
    procs = [mp.get_context("fork").Process(target=_producer, args=(q, a.data, a.sources, a.window, a.batch, a.seed + 1 + k),
                                            daemon=True) for k in range(1)]
    for p in procs:
        p.start()

    t0 = time.time()
    if a.init:
        import shutil
        shutil.copy(Path(a.init) / "ae.pt", ckpt / "ae.pt")
        threshold = json.loads((Path(a.init) / "meta.json").read_text())["plausibility_threshold_m"]
        log(f"autoencoder and threshold from {a.init}")
    else:
        ae, threshold = train_ae(cs_train, cs_val, a.ae_steps, a.seed, log)
        torch.save(ae.state_dict(), ckpt / "ae.pt")
        log(f"autoencoder trained in {time.time() - t0:.0f} s")

    # Validation: fixed clean windows of 4 s, latent at the prior mean (what N=1 runs).
    vrng = np.random.default_rng(1234)
    vstarts = ds.window_starts(cs_val, 240)
    val_batches = [to_t(ds.make_batch(cs_val, vrng.choice(vstarts, 128), 240, vrng, None)) for _ in range(4)]

    a.posterior = a.posterior or a.learned_prior
    model = CVAE(posterior=a.posterior, learned_prior=a.learned_prior)
    if a.init:
        model.load_state_dict(torch.load(Path(a.init) / "cvae.pt", weights_only=True))
    fit = [to_t(q.get()) for _ in range(8)]
    if not a.init:
        model.norm.fit(torch.cat([b["features"] for b in fit]))
    if a.posterior:
        model.target_norm.fit(torch.cat([b["gt_rel"].flatten(-2) for b in fit]))
    opt = torch.optim.Adam(model.parameters(), lr=a.lr)
    budget = a.minutes * 60
    best, best_it, it = float("inf"), -1, 0
    t1 = time.time()
    bar = Progress(int(budget), "cvae (s)")
    while time.time() - t1 < budget:
        frac = (time.time() - t1) / budget
        for g in opt.param_groups:
            g["lr"] = 1e-5 + 0.5 * (a.lr - 1e-5) * (1 + np.cos(np.pi * frac))
        b = to_t(q.get())
        model.train()
        if a.variety:
            mse, kl, bce, rot, mpjpe = variety_losses(model, b, a.variety)    # kl slot: the best-of-K term
            loss = LOSS["w_pos"] * (mse + kl) + LOSS["gamma_bce"] * bce + LOSS["w_rot"] * rot
        else:
            mse, kl, bce, rot, mpjpe = cvae_losses(model, b)
            loss = LOSS["w_pos"] * mse + LOSS["lambda_kl"] * kl + LOSS["gamma_bce"] * bce + LOSS["w_rot"] * rot
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        it += 1
        if it % 20 == 0:
            bar.n = int(time.time() - t1) - 1
            bar.update(postfix=f"it {it} train {mpjpe.item() * 100:.2f} cm kl {kl.item():.3f} bce {bce.item():.3f}")
        if it % 400 == 0 or time.time() - t1 >= budget:
            model.eval()
            with torch.no_grad():
                v = np.mean([cvae_losses(model, vb, sample=False)[4].item() for vb in val_batches]) * 100
            model.train()
            log(f"it {it} t {time.time() - t1:.0f}s lr {opt.param_groups[0]['lr']:.2e} train mpjpe {mpjpe.item() * 100:.2f} "
                f"kl {kl.item():.4f} bce {bce.item():.4f} | val mpjpe (head-anchored, no IK) {v:.2f} cm")
            if v < best:
                best, best_it = v, it
                torch.save(model.state_dict(), ckpt / "cvae.pt")
    bar.close()
    for p in procs:
        p.terminate()
    log(f"cvae: {it} iterations in {time.time() - t1:.0f} s; best val {best:.2f} cm at it {best_it}")
    meta = {"plausibility_threshold_m": threshold, "iterations": it, "best_iteration": best_it,
            "val_mpjpe_cm_training": best, "minutes": a.minutes, "sources": a.sources or sorted(ds.SOURCE_FOLDERS),
            "loss": LOSS, "posterior_encoder": a.posterior, "learned_prior": a.learned_prior, "variety": a.variety, "init": a.init, "batch": a.batch, "window": a.window, "lr": a.lr, "seed": a.seed,
            "train_clips": len(cs_train.names), "train_minutes": len(cs_train.root) / 3600}
    (ckpt / "meta.json").write_text(json.dumps(meta, indent=2))
    from models.export import export_all
    export_all(ckpt, out)
    log("exported ONNX models and manifest")


if __name__ == "__main__":
    main()
