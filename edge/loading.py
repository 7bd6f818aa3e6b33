"""Opening a model folder: its manifest verified, its int8 files checked against fp32 on this CPU
(edge.int8check), and the sessions (edge.inference) made for the precision that passed.

It sits above both: int8check compares sessions, inference makes them, and neither imports this.
"""
import sys
from pathlib import Path

from edge.inference import DEFAULT_PRECISION, Autoencoder, Decoder, make_session, model_files
from edge.int8check import REFERENCE, check_folder
from edge.modelfiles import JACOBIAN, load_manifest

_SAID = set()           # the int8 fall-backs already reported in this process


def open_models(folder=None, threads=1, precision=DEFAULT_PRECISION):
    """Verify the manifest and open both sessions: (manifest, decoder session, autoencoder session).

    int8 is checked against fp32 on this CPU first (edge.int8check); where it disagrees beyond the
    model card's bounds, the fp32 files are opened instead and the reason is said once on stderr. The
    returned manifest says what runs: manifest["files_in_use"] (decoder, autoencoder),
    manifest["precision"] (the precision in use), manifest["int8_check"]
    (the check's figures, or None) and manifest["precision_note"] ('' or why int8 is off)."""
    kw = {} if folder is None else {"folder": folder}
    listed = load_manifest(need=(), **kw)
    names = model_files(precision, listed)
    check, note = None, ""
    if precision == "int8":
        fp32 = model_files("fp32", listed)
        extra = fp32 + ((REFERENCE,) if REFERENCE in listed["files"] else ())
        manifest = load_manifest(need=tuple(dict.fromkeys(names + extra)), **kw)
        check = check_folder(manifest, Path(manifest["paths"][names[0]]).parent, names, fp32)
        if check is not None and not check.ok:
            note = f"int8 off on this CPU: {check.why}"
            names, precision = fp32, "fp32"
            if note not in _SAID:
                _SAID.add(note)
                print(f"edgepose: {note}; running the fp32 models", file=sys.stderr)
    else:
        manifest = load_manifest(need=names, **kw)
    manifest.update(precision=precision, int8_check=check and check.as_dict(), precision_note=note,
                    files_in_use=list(names))
    return manifest, make_session(manifest["paths"][names[0]], threads), make_session(manifest["paths"][names[1]], threads)


def open_jacobian(folder=None, threads=1, precision=DEFAULT_PRECISION):
    """The refiner's batch graph (models.nets.JacobianStep) for a precision: the manifest's `precisions`
    entry "jacobian" when it names one, else the fp32 graph when the folder lists it; None when the
    models have none (the refiner then differentiates with the decoder's own graph)."""
    kw = {} if folder is None else {"folder": folder}
    manifest = load_manifest(need=(), **kw)
    name = manifest.get("precisions", {}).get(precision, {}).get("jacobian", JACOBIAN)
    if name not in manifest["files"]:
        return None
    return make_session(load_manifest(need=(name,), **kw)["paths"][name], threads)


def load_models(folder=None, samples=1, threads=1, precision=DEFAULT_PRECISION):
    """Manifest, a recurrent Decoder for `samples` rows and an Autoencoder."""
    manifest, dec_s, ae_s = open_models(folder, threads, precision)
    dec = Decoder(dec_s, samples, manifest["latent"], manifest["hidden"], manifest["features"])
    return manifest, dec, Autoencoder(ae_s)
