"""Training's validation figures for saved checkpoints, on either ruler: val's clips with the sources'
skeleton conventions taken out (as training reads them now, motion.neutrals) or left in (cache v7).

    python -m models.validate CKPT_FOLDER_OR_FILE... [--data ../shared/mocap] [--conventions out|in]
        [--windows 128]

Prints, per checkpoint, the head-anchored mpjpe (no IK, the latent at the prior mean: what N=1 runs)
of the same fixed windows every training run validates on (models.train.val_batches): the unseen and
the seen people, with no extra IMUs and with random sets of them. A checkpoint folder means its
cvae.pt. This is how a run trained on one ruler is compared with one trained on the other.
"""
import argparse
import json
from pathlib import Path

import torch

from models.nets import CVAE
from models.train import val_batches, validate
from motion.pack import read_clips


def load_cvae(path):
    """A CVAE from a checkpoint file or folder, its width and features read off its weights (as
    models.export.load_checkpoint does, which needs the folder's meta and autoencoder too)."""
    path = Path(path)
    state = torch.load(path / "cvae.pt" if path.is_dir() else path, weights_only=True, map_location="cpu")
    model = CVAE(n_features=state["norm.mean"].shape[0], hidden=state["dec_gru.weight_hh_l0"].shape[1])
    model.load_state_dict(state)
    return model


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoints", nargs="+")
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--conventions", choices=("out", "in"), default="out")
    ap.add_argument("--windows", type=int, default=128)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    batches = val_batches(read_clips(a.data, "val", conventions=a.conventions == "out"), a.windows)
    for ckpt in a.checkpoints:
        model = load_cvae(ckpt)
        v = {k: round(float(validate(model, vb)), 3) for k, vb in batches.items()}
        print(json.dumps({"checkpoint": ckpt, "conventions": a.conventions, **v}))


if __name__ == "__main__":
    main()
