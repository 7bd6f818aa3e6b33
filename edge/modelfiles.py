"""Model files and their manifest: names, sha256 and the metadata the runtime needs.

The runtime refuses to start on a missing or altered model file, with a message that says what to do.
"""
import hashlib
import json
import os
from pathlib import Path

MANIFEST = "manifest.json"
# The refiner's batch (models.nets.JacobianStep); a folder without it refines with the decoder's own graph.
JACOBIAN = "decoder_jacobian.onnx"
# The shipped models; EDGEPOSE_MODELS points the runtime at another folder.
DEFAULT_DIR = Path(os.environ.get("EDGEPOSE_MODELS", Path(__file__).resolve().parent.parent / "models"))


class ModelError(RuntimeError):
    """A model file is missing, corrupt or does not match its manifest."""


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_manifest(folder, files, info):
    folder = Path(folder)
    entries = {name: {"sha256": sha256(folder / name), "bytes": (folder / name).stat().st_size} for name in files}
    (folder / MANIFEST).write_text(json.dumps({"files": entries, **info}, indent=2) + "\n")


def load_manifest(folder=DEFAULT_DIR, need=("decoder.onnx", "autoencoder.onnx")):
    """Read and verify the manifest; returns it with absolute `paths` for each file in `need`."""
    folder = Path(folder)
    mpath = folder / MANIFEST
    if not mpath.exists():
        raise ModelError(f"no {MANIFEST} in {folder}: point --models at a folder with exported models "
                         f"(python -m models.export writes one)")
    try:
        manifest = json.loads(mpath.read_text())
        files = manifest["files"]
    except (ValueError, KeyError) as e:
        raise ModelError(f"{mpath} is not a valid model manifest ({e}); re-export the models") from None
    manifest["paths"] = {}
    for name in need:
        path = folder / name
        if name not in files:
            hint = "build int8 models with the quantize tool" if ".int8." in name else "re-export (python -m models.export)"
            raise ModelError(f"{mpath} does not list {name}: {hint}")
        if not path.exists():
            raise ModelError(f"model file {path} is missing; restore it from git (git checkout -- {path}) or re-export")
        digest = sha256(path)
        if digest != files[name]["sha256"]:
            raise ModelError(f"model file {path} is corrupt or altered: sha256 {digest[:12]}... but the manifest "
                             f"says {files[name]['sha256'][:12]}...; restore it from git or re-export")
        manifest["paths"][name] = str(path)
    return manifest


def read_manifest(folder):
    path = Path(folder) / MANIFEST
    if not path.exists():
        raise ModelError(f"no {MANIFEST} in {folder}: export the fp32 models first (python -m models.export)")
    return json.loads(path.read_text())


def add_to_manifest(folder, entries, precisions=None):
    """Add or replace `entries` ({file name: extra fields}) in the manifest, keeping every other file entry
    and all metadata as they are. sha256 and bytes are computed here. `precisions` ({precision: {model:
    file}}) says which file each runtime precision opens. Written atomically."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    for name, extra in entries.items():
        p = folder / name
        manifest["files"][name] = {"sha256": sha256(p), "bytes": p.stat().st_size, **extra}
    if precisions:
        manifest.setdefault("precisions", {}).update(precisions)
    tmp = folder / (MANIFEST + ".tmp")
    tmp.write_text(json.dumps(manifest, indent=2) + "\n")
    os.replace(tmp, folder / MANIFEST)
    return manifest
