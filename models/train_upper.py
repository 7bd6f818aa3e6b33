"""Train the decoder's upper-body head (models.nets.UpperBodyHead) on a trained CVAE, choose on val's unseen
people, and export the folder with it.

    python -m models.train_upper --data ../shared/mocap [--ckpt models/checkpoints] [--minutes 12]
        [--arms-from-ik] [--out .cache/train_upper] [--export models]

The CVAE is frozen: each step draws fresh training windows as models.train does (random heading, device
noise, random IMU sets), decodes them at epsilon = 0 (what N=1 shows), and fits the head to the truth's
head-anchored joint positions (the runtime hangs the body from the headset), every joint alike, or with
--arms-from-ik every joint but the elbows and wrists, which the runtime's arm IK places (v0.5.1: so the
collars fit the shoulders, not the FK wrists; shoulders 3.27 / 2.97 cm on the unseen people against
3.83 / 3.60 fitting every joint). The first WARMUP frames of each window are left out of the loss: the
runtime's GRU state is never fresh.

The controllers carry each source's own hands (motion.hands), but CMU's and HDM05's hands stay in line
with the forearm; a person's bend. In `--bend-share` of those sources' windows the hands are bent at
the wrist (motion.synth.bend_hands: flexion std 20 deg, deviation 10, so +-60 and +-30 at 3 std; the
grips move with the hands, the wrists stay), so that the collars' MLP never learns that a controller
points along the forearm.

Chosen on val's unseen people in the 4-point case (no extra IMU): the mean head-anchored joint error,
checked every --every seconds; the shoulders are printed beside it. v0.5.1's head trained 24 minutes on
2 CPU cores (its best step came at 7; the 32-wide head has 12 k weights); the log goes to
OUT/train_upper_log.txt.
"""
import argparse
import json
import shutil
import time
from dataclasses import fields
from pathlib import Path

import numpy as np
import torch

from edge.imus import ImuNoise
from edge.progress import Progress
from edge.signals import Signals
from edge.skeleton import JOINT
from models.export import export_all, load_checkpoint
from models.nets import LATENT, UpperBodyHead
from models.train import head_positions
from motion import dataset as ds
from motion.pack import read_clips
from motion.synth import DeviceNoise, bend_hands

WINDOW, WARMUP = 90, 30
R_STD_FLOOR = 0.05
# Sources whose hands stay in line with the forearm (python -m motion.hands: roll only)
UNBENT_FOLDERS = ("cmu_amc2bvh", "cmu_cgspeed_mb", "hdm05_ccbysa")
REPORT = ("neck", "l_collar", "r_collar", "l_shoulder", "r_shoulder", "pelvis", "l_knee", "r_knee")


def unbent_clips(cs):
    """[clips] bool: the clip's source has hands that never bend at the wrist."""
    return np.array([any(f"/{f}/" in f"/{n}" for f in UNBENT_FOLDERS) for n in cs.names])


def bend_some(rng, starts, cs, unbent, share):
    """The `hands` hook of motion.dataset.make_batch: bend the hands of `share` of the windows whose
    source does not bend them."""
    clip = np.searchsorted(cs.starts, starts, side="right") - 1
    pick = unbent[clip] & (rng.random(len(starts)) < share)

    def hands(sig):
        if pick.any():
            bent = bend_hands(Signals(**{f.name: getattr(sig, f.name)[:, pick] for f in fields(sig)}), ds.FPS, rng)
            sig.hand_rot[:, pick], sig.hand_pos[:, pick] = bent.hand_rot, bent.hand_pos
        return sig
    return hands


class Windows:
    """Decoded training or validation windows: the decoder features with orientations [W,B,91], the frozen
    CVAE's 6D at epsilon = 0 [W,B,120], the puck in the yaw frame and the head-anchored truth."""

    def __init__(self, cvae, cs, seed, batch, imus=True, bend_share=0.0):
        self.cvae, self.cs, self.batch, self.imus = cvae, cs, batch, imus
        self.rng = np.random.default_rng(seed)
        self.starts = ds.window_starts(cs, WINDOW)
        self.noise, self.imu_noise = DeviceNoise(), ImuNoise()
        self.unbent, self.bend_share = unbent_clips(cs), bend_share

    def draw(self):
        starts = self.rng.choice(self.starts, self.batch)
        hands = bend_some(self.rng, starts, self.cs, self.unbent, self.bend_share) if self.bend_share else None
        b = ds.make_batch(self.cs, starts, WINDOW, self.rng, self.noise, self.imu_noise, self.imus, hands, orientations=True)
        x = torch.from_numpy(b["features"])
        with torch.no_grad():
            rot, _, _ = self.cvae.decode(x, torch.zeros(x.shape[:-1] + (LATENT,)))
        keep = slice(WARMUP, None)
        return {"features": torch.from_numpy(np.concatenate([b["features"], b["orient"]], -1)[keep]),
                "rot6d": rot[keep], "root_rot": torch.from_numpy(b["root_rot"][keep]),
                "gt_rel": torch.from_numpy(b["gt_rel"][keep])}


def joint_errors(head, batches):
    """Mean head-anchored error per joint (cm) over the batches of the 6D head(features, rot6d) makes."""
    e = 0.0
    with torch.no_grad():
        for b in batches:
            e = e + (head_positions(head(b["features"], b["rot6d"]), b["root_rot"]) - b["gt_rel"]).norm(dim=-1).mean((0, 1))
    return (e * 100 / len(batches)).numpy()


def cvae_alone(features, rot6d):
    return rot6d


def fit_normalizers(head, batches):
    f = torch.cat([b["features"].reshape(-1, b["features"].shape[-1]) for b in batches])
    r = torch.cat([b["rot6d"].reshape(-1, 120)[:, :head.norm_r.mean.shape[0]] for b in batches])
    head.norm_f.fit(f)
    head.norm_r.fit(r)
    # Some of the CVAE's 6D hardly move (its head and wrists: std 0.001). Normalised by that, int8's
    # rounding of them (about 0.01) reads as 10 std and the head amplified it: the int8 decoder strayed
    # 0.13 in 6D from fp32 on the bundled walk. A floor makes such columns count for what they carry.
    head.norm_r.std.clamp_(min=R_STD_FLOOR)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--ckpt", default="models/checkpoints", help="the trained CVAE and autoencoder")
    ap.add_argument("--out", default=".cache/train_upper", help="checkpoint folder (the CVAE's files and upper.pt)")
    ap.add_argument("--export", default=None, help="export the folder's ONNX models here (then: python -m quantize)")
    ap.add_argument("--minutes", type=float, default=12.0)
    ap.add_argument("--hidden", type=int, default=32, help="each MLP's width (v0.5: 32; 64 measured too)")
    ap.add_argument("--batch", type=int, default=64, help="windows per step")
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--bend-share", type=float, default=0.5)
    ap.add_argument("--every", type=float, default=60.0, help="seconds between validations")
    ap.add_argument("--val-batches", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--arms-from-ik", action="store_true",
                    help="fit and choose on every joint but the elbows and wrists, which the runtime's arm IK "
                         "puts on the controllers (so the collars fit the shoulders, not the FK wrists)")
    ap.add_argument("--source-conventions", action="store_true",
                    help="train and choose on clips with each source's skeleton conventions left in (the old ruler; "
                         "for a CVAE trained with models.train --source-conventions)")
    a = ap.parse_args(argv)
    torch.manual_seed(a.seed)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    logf = open(out / "train_upper_log.txt", "a")

    def log(msg):
        print(msg, flush=True)
        logf.write(msg + "\n")
        logf.flush()

    cvae, _, meta = load_checkpoint(a.ckpt)
    for p in cvae.parameters():
        p.requires_grad_(False)
    train = read_clips(a.data, "train", conventions=not a.source_conventions)
    val = read_clips(a.data, "val", conventions=not a.source_conventions)
    if val.people is None or not (val.people == "unseen").any():
        raise SystemExit(f"{a.data}: val has no unseen people to choose on (MANIFEST.tsv)")
    val = val.subset(val.people == "unseen")
    draws = Windows(cvae, train, a.seed, a.batch, bend_share=a.bend_share)
    val_windows = Windows(cvae, val, a.seed + 1, 128, imus=False)
    val_batches = [val_windows.draw() for _ in range(a.val_batches)]
    head = UpperBodyHead(a.hidden)
    fit_normalizers(head, [draws.draw() for _ in range(8)])
    opt = torch.optim.Adam([p for n, p in head.named_parameters() if not n.startswith("norm")], a.lr)
    log(f"upper-body head: hidden {a.hidden}, {sum(p.numel() for p in head.parameters())} weights; "
        f"train {len(train.names)} clips, val unseen {len(val.names)} clips; {a.minutes:g} min on {torch.get_num_threads()} threads")
    fitted = np.ones(len(JOINT), dtype=bool)        # the joints the loss and the choice count
    if a.arms_from_ik:
        fitted[[JOINT[f"{s}_{j}"] for s in "lr" for j in ("elbow", "wrist")]] = False
    log(f"fitted joints: {'all but the elbows and wrists (the arm IK places them)' if a.arms_from_ik else 'all'}")
    per_joint = joint_errors(cvae_alone, val_batches)
    before = per_joint[fitted]
    best, best_state, step, t0, last = float(before.mean()), None, 0, time.time(), time.time()
    log("CVAE alone (val unseen, 4-point): mean " + f"{before.mean():.3f} cm, "
        + ", ".join(f"{n} {per_joint[JOINT[n]]:.2f}" for n in REPORT))
    end = t0 + 60 * a.minutes
    with Progress(int(60 * a.minutes), "train upper-body head") as bar:
        while time.time() < end:
            b = draws.draw()
            err = head_positions(head(b["features"], b["rot6d"]), b["root_rot"]) - b["gt_rel"]
            loss = (err[..., torch.from_numpy(fitted), :] ** 2).sum(-1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            step += 1
            frac = (time.time() - t0) / (60 * a.minutes)
            for g in opt.param_groups:          # cosine decay over the run's wall clock
                g["lr"] = a.lr * 0.5 * (1 + np.cos(np.pi * min(frac, 1.0)))
            if time.time() - last > a.every or time.time() >= end:
                last = time.time()
                e = joint_errors(head, val_batches)
                score, mark = float(e[fitted].mean()), ""
                if score < best:
                    best, best_state, mark = score, {k: v.clone() for k, v in head.state_dict().items()}, " (best)"
                log(f"step {step} {time.time() - t0:.0f}s loss {loss.item() * 1e4:.1f}: val unseen mean {score:.3f} cm, "
                    + ", ".join(f"{n} {e[JOINT[n]]:.2f}" for n in REPORT) + mark)
            bar.update(int(time.time() - t0) - bar.n, postfix=f"step {step} loss {loss.item() * 1e4:.1f}")
    if best_state is None:
        raise SystemExit("the head never beat the CVAE alone on val's unseen people: nothing saved")
    head.load_state_dict(best_state)
    for name in ("cvae.pt", "ae.pt", "meta.json"):
        if Path(a.ckpt, name).resolve() != (out / name).resolve():
            shutil.copyfile(Path(a.ckpt) / name, out / name)
    torch.save(head.state_dict(), out / "upper.pt")
    info = {"hidden": a.hidden, "steps": step, "minutes": a.minutes, "batch": a.batch, "window": WINDOW,
            "warmup": WARMUP, "lr": a.lr, "bend_share": a.bend_share, "seed": a.seed, "ckpt": a.ckpt, "source_conventions": a.source_conventions,
            "arms_from_ik": a.arms_from_ik,
            "val_unseen_mean_cm": {"cvae": float(before.mean()), "with_head": best}}
    (out / "upper_meta.json").write_text(json.dumps(info, indent=2) + "\n")
    log(f"saved {out}/upper.pt: val unseen mean {before.mean():.3f} -> {best:.3f} cm")
    if a.export:
        export_all(out, a.export)
        log(f"exported {a.export}; now: python -m quantize --models {a.export}")


if __name__ == "__main__":
    main()
