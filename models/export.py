"""Export the trained networks as one-step ONNX graphs and write models/manifest.json.

    python -m models.export [--ckpt .cache/train] [--out models]
    python -m models.export --ckpt models/checkpoints --jacobian-only      (add only the refiner's batch)

Three graphs: the decoder step, the pose autoencoder, and the refiner's batch (JacobianStep: the
decoder's rotations for many latents on one frame's inputs). All are exported in inference form (models.nets.DecoderStep, AEStep): normalisation folded into the
first layer, the decoder's GRU written out as Gemm + Sigmoid/Tanh with its two gates in one Gemm
(ONNX Runtime cannot quantize the ONNX GRU op, and PyTorch has mis-exported nn.GRU before).
"""
import argparse
import json
import shutil
from pathlib import Path

import torch

from edge.modelfiles import JACOBIAN, add_to_manifest, write_manifest
from edge.skeleton import JOINT_NAMES, NUM_JOINTS, PARENTS
from models.nets import CVAE, LATENT, AEStep, DecoderStep, JacobianStep, PoseAE, UpperBodyHead


def load_upper(ckpt):
    """The upper-body head (models.train_upper) in a checkpoint folder, or None where it has none."""
    path = Path(ckpt) / "upper.pt"
    if not path.exists():
        return None
    state = torch.load(path, weights_only=True, map_location="cpu")
    head = UpperBodyHead(hidden=state["torso.mid.weight"].shape[0])
    head.load_state_dict(state)
    return head.eval()


def decoder_features(cvae, upper):
    """The decoder graph's input width: the CVAE's features, and the orientations its upper-body head reads."""
    return upper.norm_f.mean.shape[0] if upper is not None else cvae.n_features


def load_checkpoint(ckpt):
    ckpt = Path(ckpt)
    meta = json.loads((ckpt / "meta.json").read_text())
    state = torch.load(ckpt / "cvae.pt", weights_only=True, map_location="cpu")
    cvae = CVAE(posterior=meta.get("posterior_encoder", False), learned_prior=meta.get("learned_prior", False),
                n_features=state["norm.mean"].shape[0], hidden=state["dec_gru.weight_hh_l0"].shape[1])
    ae = PoseAE()
    cvae.load_state_dict(state)
    ae.load_state_dict(torch.load(ckpt / "ae.pt", weights_only=True, map_location="cpu"))
    return cvae.eval(), ae.eval(), meta


def export_decoder(cvae, path, upper=None):
    step = DecoderStep(cvae, upper).eval()
    n = 4
    args = (torch.zeros(n, decoder_features(cvae, upper)), torch.zeros(n, LATENT), torch.zeros(n, cvae.hidden))
    torch.onnx.export(step, args, str(path), dynamo=False, external_data=False, opset_version=17,
                      input_names=["features", "latent", "hidden"],
                      output_names=["rot6d", "contacts", "hidden_out"],
                      dynamic_axes={"features": {0: "M"},     # M: N rows, or 1 that every row shares
                                    **{k: {0: "N"} for k in ("latent", "hidden", "rot6d", "contacts", "hidden_out")}})


def export_jacobian(cvae, path, upper=None):
    """The refiner's batch (models.nets.JacobianStep): one frame's features and GRU state, R latents."""
    args = (torch.zeros(1, decoder_features(cvae, upper)), torch.zeros(4, LATENT), torch.zeros(1, cvae.hidden))
    torch.onnx.export(JacobianStep(cvae, upper).eval(), args, str(path), dynamo=False, external_data=False, opset_version=17,
                      input_names=["features", "latent", "hidden"], output_names=["rot6d"],
                      dynamic_axes={"latent": {0: "R"}, "rot6d": {0: "R"}})


def export_autoencoder(ae, path):
    torch.onnx.export(AEStep(ae).eval(), (torch.zeros(4, NUM_JOINTS * 3),), str(path), dynamo=False, external_data=False,
                      opset_version=17, input_names=["positions"], output_names=["rot6d"],
                      dynamic_axes={"positions": {0: "N"}, "rot6d": {0: "N"}})


def export_all(ckpt, out):
    out = Path(out)
    cvae, ae, meta = load_checkpoint(ckpt)
    upper = load_upper(ckpt)
    export_decoder(cvae, out / "decoder.onnx", upper)
    export_autoencoder(ae, out / "autoencoder.onnx")
    export_jacobian(cvae, out / JACOBIAN, upper)
    info = {
        "fps": 60.0, "latent": LATENT, "hidden": cvae.hidden, "features": decoder_features(cvae, upper),
        "joint_names": list(JOINT_NAMES), "parents": PARENTS.tolist(),
        "plausibility_threshold_m": meta["plausibility_threshold_m"],
        "training": {k: v for k, v in meta.items() if k != "plausibility_threshold_m"},
    }
    if upper is not None:
        info["upper_body_head"] = json.loads((Path(ckpt) / "upper_meta.json").read_text())
    # the runtime's SSI selection settings (bench/tune_selection.py) belong to the folder, not the weights:
    # a re-export keeps them (their `chosen_on` says which model they were chosen on)
    earlier = out / "manifest.json"
    if earlier.exists() and "selection" in json.loads(earlier.read_text()):
        info["selection"] = json.loads(earlier.read_text())["selection"]
    write_manifest(out, ["decoder.onnx", "autoencoder.onnx", JACOBIAN], info)
    # Keep the PyTorch weights beside the ONNX files: the parity tests compare the two.
    (out / "checkpoints").mkdir(exist_ok=True)
    for name in ("cvae.pt", "ae.pt", "meta.json") + (("upper.pt", "upper_meta.json") if upper is not None else ()):
        if (Path(ckpt) / name).resolve() != (out / "checkpoints" / name).resolve():
            shutil.copyfile(Path(ckpt) / name, out / "checkpoints" / name)


def add_jacobian(ckpt, out):
    """Export only the refiner's batch into a folder whose other models are already there, and list it
    in their manifest (the other files and their digests stay as they are)."""
    cvae, _, _ = load_checkpoint(ckpt)
    export_jacobian(cvae, Path(out) / JACOBIAN, load_upper(ckpt))
    add_to_manifest(out, {JACOBIAN: {"source_checkpoint": "checkpoints/cvae.pt"}})


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", default=".cache/train")
    ap.add_argument("--out", default="models")
    ap.add_argument("--jacobian-only", action="store_true",
                    help=f"export only {JACOBIAN} (the refiner's batch) beside models already there")
    a = ap.parse_args()
    if a.jacobian_only:
        add_jacobian(a.ckpt, a.out)
        print(f"wrote {a.out}/{JACOBIAN} and listed it in {a.out}/manifest.json")
        return
    export_all(a.ckpt, a.out)
    print(f"wrote {a.out}/decoder.onnx, {a.out}/autoencoder.onnx, {a.out}/manifest.json; "
          f"now build the int8 models the runtime defaults to: python -m quantize --models {a.out}")
    if "selection" not in json.loads((Path(a.out) / "manifest.json").read_text()):
        print(f"note: {a.out}/manifest.json has no SSI selection settings, so N > 1 selects on the autoencoder "
              f"alone; copy `selection` from models/manifest.json, or choose them on val "
              f"(bench/tune_selection.py, bench/legs_apart.py --models {a.out})")


if __name__ == "__main__":
    main()
