"""Per-frame cost of the whole SSI pipeline on one core, at several N, in one run.

    python bench/pipeline.py [--samples 1,10,32,100] [--frames 600] [--precision fp32] [--json OUT]
    python bench/pipeline.py --compare [--samples 1,10,32,100] [--frames 600] [--blocks 10] [--json OUT]
    python bench/pipeline.py --trackers [--samples 100] [--frames 3000] [--blocks 30] [--json OUT]
    python bench/pipeline.py --against REV [--samples 1,32,100] [--frames 600] [--blocks 10] [--precision int8]
    python bench/pipeline.py --models-against DIR [--samples 1,16] [--frames 600] [--blocks 10] [--precision int8]
    python bench/pipeline.py --refine [--samples 1,32] [--frames 600] [--blocks 10] [--precision int8]

Plain run: the pipeline with --precision models, then its bare decoder call; medians and p99 in
microseconds and the pipeline / decoder ratio.

--compare (needs torch) times, per N, in one process:
  pipeline_fp32, pipeline_int8   the pipeline with fp32 and with int8 models (speed-up = fp32 / int8)
  decoder_ort, decoder_torch     one bare decoder step on the pipeline's rows in ONNX Runtime, and in
                                 PyTorch eager run per frame as research code runs it (bench/reference.py)
  decoder_ort_int8               the same bare step with the int8 decoder
  pipeline_reference             the fp32 pipeline with its decoders swapped for that PyTorch eager step
  pipeline_numpy                 the fp32 pipeline without the compiled core (edge/native): numpy only
Each is warmed, then all take turns in --blocks blocks of --frames / --blocks calls (the order
rotating block by block), so machine noise hits every side alike. Ratios are p50 / p50 over all timed
calls, with the range of the per-block ratios; the fp32 pipeline / ORT decoder ratio of the plain run
is reported too. Before timing, the PyTorch and ONNX decoders are run on the same inputs and must agree (max abs
difference < 1e-4).

--trackers times, per N, the default (int8) pipeline fed the bundled walk with no extra IMUs and with
all seven worn (edge.imus; the decoder's IMU inputs and each segment's measured rotation), interleaved
the same way; the ratio is all seven / none.

--against REV times another git revision's pipeline (and its bare decoder) interleaved with this
tree's, to show a regression (or a fix) in one command: REV is checked out with `git archive` into a
temporary folder, and each tree runs in a worker process of its own (its own code and models), both
pinned to the same core and taking turns block by block in alternating order, so only one runs at a
time and machine noise hits both alike. Printed per N: each side's pipeline and decoder p50 / p99,
pipeline / decoder, and this tree / REV with the range of the per-block ratios.

--models-against DIR times this tree's code on two model folders, the shipped models/ and DIR (a
candidate of another size), the same way as --against: one worker each, pinned, taking turns.

--refine times latent refinement (edge.refine) against what it is built from: one refinement step
(the batch's decode of the latent, its 30 steps and the sample's own latent on the Jacobian graph,
then FK, the terms' residuals and the 30x30 solve in C) against one bare decoder call on N=31 rows,
taking turns call by call; and, per N, interleaved in blocks, the whole frame with a live target at
K=1, 2, 3 steps against the frame without one, with p99. Prints DragPoser's published per-iteration
cost (desktop i7, PyTorch, section 5) beside ours.

Pins itself to one core (like the board's budget). A benchmark, not a test: it prints figures and,
besides that agreement check, asserts nothing.
"""
import argparse
import json
import os
import platform
import sys
from pathlib import Path

import numpy as np
import onnxruntime

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from edge.inference import Decoder
from edge.loading import open_models
from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from motion.takes import from_sample
from motion.timing import time_alternating, time_calls

SAMPLE = Path(__file__).resolve().parent.parent / "samples" / "cmu_09_12_walk.npz"
WARMUP = 120
PARITY_TOL = 1e-4
# name: (numerator, denominator) of each --compare ratio
RATIOS = {
    "int8_speedup": ("pipeline_fp32", "pipeline_int8"),
    "decoder_torch_over_ort": ("decoder_torch", "decoder_ort"),
    "pipeline_reference_over_ours": ("pipeline_reference", "pipeline_fp32"),
    "pipeline_over_decoder": ("pipeline_fp32", "decoder_ort"),
    "compiled_core_speedup": ("pipeline_numpy", "pipeline_fp32"),
    "decoder_int8_speedup": ("decoder_ort", "decoder_ort_int8"),
}


def machine(**versions):
    cpu = platform.processor()
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                   if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {"platform": platform.platform(), "cpu": cpu, "python": platform.python_version(),
            "numpy": np.__version__, "onnxruntime": onnxruntime.__version__, **versions}


def summary(us):
    return {"p50": float(np.median(us)), "p99": float(np.percentile(us, 99))}


def warm(pipe, frames):
    for t in range(WARMUP):
        pipe.step(frames[t % len(frames)])


def plain(a, frames, ns):
    rows = []
    print(f"{'N':>4} {'pipeline p50':>13} {'p99':>8} {'decoder p50':>12} {'p99':>8} {'ratio':>6}   (microseconds, one core)")
    for n in ns:
        pipe = Pipeline(PipelineOptions(samples=n, precision=a.precision))
        warm(pipe, frames)
        whole = time_calls(lambda i, pipe=pipe: pipe.step(frames[(i + WARMUP) % len(frames)]), a.frames)
        bare = time_calls(lambda i, pipe=pipe: pipe.decoder.step(), a.frames)
        r = {"samples": n, "pipeline_us": summary(whole), "decoder_us": summary(bare)}
        r["ratio_p50"] = r["pipeline_us"]["p50"] / r["decoder_us"]["p50"]
        rows.append(r)
        print(f"{n:>4} {r['pipeline_us']['p50']:>13.0f} {r['pipeline_us']['p99']:>8.0f} "
              f"{r['decoder_us']['p50']:>12.0f} {r['decoder_us']['p99']:>8.0f} {r['ratio_p50']:>6.2f}")
    return {"precision": a.precision, "machine": machine(), "results": rows}


def interleaved(calls, blocks, per_block):
    """Time calls[name](t) for t = WARMUP.., all names taking turns block by block in rotating order.
    Returns {name: microseconds [blocks, per_block]}."""
    names = list(calls)
    out = {k: np.empty((blocks, per_block)) for k in names}
    for b in range(blocks):
        t0 = WARMUP + b * per_block
        for k in names[b % len(names):] + names[:b % len(names)]:
            out[k][b] = time_calls(lambda i, k=k, t0=t0: calls[k](t0 + i), per_block)
    return out


def ratio(times, num, den):
    per_block = np.median(times[num], axis=1) / np.median(times[den], axis=1)
    return {"p50": float(np.median(times[num]) / np.median(times[den])),
            "blocks_min": float(per_block.min()), "blocks_max": float(per_block.max())}


def primed(dec, src):
    """`dec` holding src's inputs and GRU state: a decoder of its own, so timing it leaves src alone."""
    dec.features[:] = src.features
    dec.latent[:] = src.latent
    dec.state[:] = src.state
    return dec


def compare(a, frames, ns):
    import torch   # only --compare needs torch
    from reference import TorchDecoder, load_step, max_abs_diff, reference_pipeline

    model = load_step()
    manifest, session, _ = open_models(precision="fp32")
    diff = max_abs_diff(session, model, manifest)
    print(f"PyTorch vs ONNX decoder step, same inputs: max abs diff {diff:.2e} (tolerance {PARITY_TOL:.0e})")
    if not diff < PARITY_TOL:
        sys.exit("the PyTorch reference does not match the ONNX decoder; not timing it")
    per_block = a.frames // a.blocks
    print(f"\np50 per frame in microseconds, one core; ratio p50/p50 [min, max over {a.blocks} blocks of {per_block}]")
    print(f"{'N':>4} {'fp32 pipe':>10} {'int8 pipe':>10} {'speed-up fp32/int8':>20} "
          f"{'ORT dec':>8} {'torch dec':>10} {'torch/ORT':>18} {'ref pipe':>9} {'ref/ours':>18} {'pipe/dec':>20} "
          f"{'numpy pipe':>11} {'numpy/ours':>18} {'int8 dec':>9} {'dec fp32/int8':>18}")
    rows = []
    for n in ns:
        pipes = {"pipeline_fp32": Pipeline(PipelineOptions(samples=n, precision="fp32")),
                 "pipeline_int8": Pipeline(PipelineOptions(samples=n, precision="int8")),
                 "pipeline_reference": reference_pipeline(model, n),
                 "pipeline_numpy": Pipeline(PipelineOptions(samples=n, precision="fp32", use_native=False))}
        for pipe in pipes.values():
            warm(pipe, frames)
        ours, m = pipes["pipeline_fp32"], pipes["pipeline_fp32"].manifest
        dims = ours.rows, m["latent"], m["hidden"], m["features"]
        decoders = {"decoder_ort": primed(Decoder(ours.decoder.session, *dims), ours.decoder),
                    "decoder_ort_int8": primed(Decoder(pipes["pipeline_int8"].decoder.session, *dims), ours.decoder),
                    "decoder_torch": primed(TorchDecoder(model, *dims), ours.decoder)}
        for dec in decoders.values():
            for _ in range(WARMUP):
                dec.step()
        calls = {k: (lambda t, p=p: p.step(frames[t % len(frames)])) for k, p in pipes.items()}
        calls.update({k: (lambda t, d=d: d.step()) for k, d in decoders.items()})
        times = interleaved(calls, a.blocks, per_block)
        r = {"samples": n, "rows": ours.rows, "us": {k: summary(v) for k, v in times.items()},
             "ratios": {k: ratio(times, *v) for k, v in RATIOS.items()},
             "ssi_switches": {k: p.switch_count for k, p in pipes.items()}}
        rows.append(r)
        us = {k: f"{v['p50']:.0f}" for k, v in r["us"].items()}
        rs = {k: f"{v['p50']:.2f} [{v['blocks_min']:.2f},{v['blocks_max']:.2f}]" for k, v in r["ratios"].items()}
        print(f"{n:>4} {us['pipeline_fp32']:>10} {us['pipeline_int8']:>10} {rs['int8_speedup']:>20} "
              f"{us['decoder_ort']:>8} {us['decoder_torch']:>10} {rs['decoder_torch_over_ort']:>18} "
              f"{us['pipeline_reference']:>9} {rs['pipeline_reference_over_ours']:>18} {rs['pipeline_over_decoder']:>20} "
              f"{us['pipeline_numpy']:>11} {rs['compiled_core_speedup']:>18} {us['decoder_ort_int8']:>9} "
              f"{rs['decoder_int8_speedup']:>18}")
    method = {
        "cores": 1, "warmup_calls": WARMUP, "blocks": a.blocks, "calls_per_block": per_block,
        "schedule": "all contestants in one process, taking turns block by block in rotating order",
        "statistic": "p50/p99 over all timed calls; ratio = p50/p50, blocks_min/max = range of per-block p50 ratios",
        "sample": SAMPLE.name,
        "reference": "models.nets.DecoderStep from models/checkpoints in PyTorch eager, one thread, per frame: "
                     "torch.from_numpy inputs, no_grad forward, .numpy() copies back (bench/reference.py)",
    }
    return {"method": method, "machine": machine(torch=torch.__version__),
            "parity_max_abs_diff": diff, "results": rows}


def trackers(a, frames, ns):
    """The frame with all seven extra IMUs against the frame with none, interleaved (same model)."""
    from edge.imus import IMU_LOCATIONS, ImuNoise, mask
    from motion.synth import wear
    take = from_sample(SAMPLE)
    worn = wear(take.signals, mask(IMU_LOCATIONS), take.fps, np.random.default_rng(0), ImuNoise())
    worn_frames = [worn.slice(t, t + 1) for t in range(take.frames)]
    per_block = a.frames // a.blocks
    rows = []
    print(f"{'N':>4} {'none p50':>9} {'all seven p50':>14} {'all/none':>20}   (microseconds, one core, int8)")
    for n in ns:
        pipes = {"none": (Pipeline(PipelineOptions(samples=n)), frames), "all_seven": (Pipeline(PipelineOptions(samples=n)), worn_frames)}
        if not pipes["none"][0].imus:
            sys.exit("the shipped decoder reads no extra IMUs: nothing to compare")
        for p, f in pipes.values():
            warm(p, f)
        calls = {k: (lambda t, p=p, f=f: p.step(f[t % len(f)])) for k, (p, f) in pipes.items()}
        times = interleaved(calls, a.blocks, per_block)
        r = {"samples": n, "us": {k: summary(v) for k, v in times.items()}, "ratio": ratio(times, "all_seven", "none")}
        rows.append(r)
        q = r["ratio"]
        print(f"{n:>4} {r['us']['none']['p50']:>9.0f} {r['us']['all_seven']['p50']:>14.0f} "
              f"{q['p50']:>8.3f} [{q['blocks_min']:.2f},{q['blocks_max']:.2f}]")
    return {"machine": machine(), "blocks": a.blocks, "calls_per_block": per_block, "results": rows}


def refine_bench(a, frames, ns):
    """One refinement step against one N=31 decoder batch, and the frame with K steps against without."""
    from edge.skeleton import JOINT
    per_block = a.frames // a.blocks
    rows = []

    def targeted(n, steps):
        pipe = Pipeline(PipelineOptions(samples=n, precision=a.precision, refine={"steps": steps}))
        warm(pipe, frames)
        # a target on the left toe that never ends, 40 cm above where the body is: refinement every frame
        pipe.refiner.add_target("l_toe", pipe.out.positions[JOINT["l_toe"]] + [0.0, 0.4, 0.2], radius=0.0,
                                first=0, last=1 << 40)
        for t in range(30):
            pipe.step(frames[(WARMUP + t) % len(frames)])
        return pipe

    one = targeted(1, 1)
    r, m = one.refiner, one.manifest
    z = one.decoder.latent[0].astype(np.float64)
    zp = one.latents[0].astype(np.float64)
    dec31 = Decoder(one.decoder.session, 31, m["latent"], m["hidden"], m["features"], recurrent=False)
    r.z_prev[:], r.z_prior[:] = z, zp

    def refine_step(t):
        r.z[:] = z              # every call steps from the same latent
        return r.step()

    calls = {"refine_step": refine_step, "decoder_n31": lambda t: dec31.step()}
    for k in calls:                 # warm both
        time_calls(calls[k], WARMUP)
    # call by call in turns (these two are short: a block of either would see another machine state)
    times = {k: v.reshape(a.blocks, per_block) for k, v in time_alternating(calls, a.blocks * per_block).items()}
    step = {"us": {k: summary(v) for k, v in times.items()}, "ratio": ratio(times, "refine_step", "decoder_n31")}
    q = step["ratio"]
    print(f"one refinement step {step['us']['refine_step']['p50']:.0f} us (p99 {step['us']['refine_step']['p99']:.0f}); "
          f"one N=31 decoder call {step['us']['decoder_n31']['p50']:.0f} us: ratio {q['p50']:.2f} "
          f"[{q['blocks_min']:.2f}, {q['blocks_max']:.2f}]   ({a.precision}, one core)")
    print("DragPoser (section 5, desktop i7, PyTorch, per iteration): decoder 630 us + losses 4,590 us + "
          "backprop 6,910 us = 12,130 us")
    print(f"\n{'N':>4} {'no target p50':>14} {'p99':>7} " + " ".join(f"{'K=' + str(k) + ' p50':>10} {'p99':>7}"
                                                              for k in (1, 2, 3)) + "   (frame, microseconds)")
    for n in ns:
        pipes = {"none": Pipeline(PipelineOptions(samples=n, precision=a.precision, refine=True))}
        warm(pipes["none"], frames)
        pipes.update({f"K={k}": targeted(n, k) for k in (1, 2, 3)})
        calls = {k: (lambda t, p=p: p.step(frames[t % len(frames)])) for k, p in pipes.items()}
        times = interleaved(calls, a.blocks, per_block)
        row = {"samples": n, "us": {k: summary(v) for k, v in times.items()}}
        rows.append(row)
        u = row["us"]
        print(f"{n:>4} {u['none']['p50']:>14.0f} {u['none']['p99']:>7.0f} "
              + " ".join(f"{u[f'K={k}']['p50']:>10.0f} {u[f'K={k}']['p99']:>7.0f}" for k in (1, 2, 3)))
    return {"machine": machine(), "precision": a.precision, "blocks": a.blocks, "calls_per_block": per_block,
            "refine_step": step, "frames": rows,
            "dragposer_per_iteration_us": {"decoder": 630, "losses": 4590, "backprop": 6910, "total": 12130}}


def against(a, ns):
    """This tree's pipeline against revision a.against's (or against the models in a.models_against),
    each in its own worker, interleaved."""
    import subprocess
    import tarfile
    import tempfile
    here = Path(__file__).resolve().parent.parent
    with tempfile.TemporaryDirectory() as tmp:
        models = {}
        if a.models_against:
            rev = "cand"
            trees = {"this": here, rev: here}
            models = {rev: str(Path(a.models_against).resolve())}
            a.against = a.models_against
        else:
            arch = subprocess.run(["git", "archive", a.against], cwd=here, check=True, capture_output=True).stdout
            with tarfile.open(fileobj=__import__("io").BytesIO(arch)) as tar:
                tar.extractall(tmp, filter="data")
            rev = subprocess.run(["git", "rev-parse", "--short", a.against], cwd=here, check=True, capture_output=True,
                                 text=True).stdout.strip()
            trees = {"this": here, rev: Path(tmp)}
        # Each side reads its own tree's bundled sample: an older tree may not read a newer sample file
        # (e598c25's Signals has no extra IMUs). Said when the two differ.
        samples = {side: tree / "samples" / SAMPLE.name if (tree / "samples" / SAMPLE.name).exists() else SAMPLE
                   for side, tree in trees.items()}
        per_block = a.frames // a.blocks
        rows = []
        print(f"this tree against {a.against} ({rev}), {a.precision}, one core; p50 (p99) microseconds; "
              f"{a.blocks} blocks of {per_block} interleaved")
        if samples["this"].read_bytes() != samples[rev].read_bytes():
            print(f"(each side fed its own tree's {SAMPLE.name}: the two files differ)")
        print(f"{'N':>4} {'side':>8} {'pipeline':>16} {'decoder':>14} {'pipe/dec':>9}   this/{rev} pipeline [blocks]")
        for n in ns:
            procs = {}
            for side, tree in trees.items():
                env = dict(os.environ, PYTHONPATH=str(tree))
                procs[side] = subprocess.Popen(
                    [sys.executable, str(Path(__file__).resolve().parent / "pipeline_worker.py"), str(n), a.precision,
                     str(samples[side]), str(WARMUP)] + ([models[side]] if side in models else []), cwd=tree, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                    text=True)
            for p in procs.values():
                json.loads(p.stdout.readline())     # warmed
            times = {(side, what): np.empty((a.blocks, per_block)) for side in trees for what in ("pipeline", "decoder")}
            for b in range(a.blocks):
                for side in (list(trees) if b % 2 == 0 else list(trees)[::-1]):
                    for what in ("pipeline", "decoder"):
                        procs[side].stdin.write(f"{what} {per_block}\n")
                        procs[side].stdin.flush()
                        times[side, what][b] = json.loads(procs[side].stdout.readline())
            for p in procs.values():
                p.stdin.close()
                p.wait()
            r = {"samples": n, "sides": {}}
            for side in trees:
                pipe_t, dec_t = times[side, "pipeline"], times[side, "decoder"]
                r["sides"][side] = {"pipeline_us": summary(pipe_t), "decoder_us": summary(dec_t),
                                    "pipeline_over_decoder": float(np.median(pipe_t) / np.median(dec_t))}
            per = np.median(times["this", "pipeline"], axis=1) / np.median(times[rev, "pipeline"], axis=1)
            r["this_over_rev"] = {"p50": float(np.median(times["this", "pipeline"]) / np.median(times[rev, "pipeline"])),
                                  "blocks_min": float(per.min()), "blocks_max": float(per.max())}
            rows.append(r)
            for side in trees:
                q = r["sides"][side]
                print(f"{n:>4} {side:>8} {q['pipeline_us']['p50']:>8.0f} ({q['pipeline_us']['p99']:>5.0f}) "
                      f"{q['decoder_us']['p50']:>6.0f} ({q['decoder_us']['p99']:>5.0f}) {q['pipeline_over_decoder']:>9.2f}"
                      + (f"   {r['this_over_rev']['p50']:.3f} [{per.min():.2f}, {per.max():.2f}]" if side == "this" else ""))
    return {"against": a.against, "revision": rev, "precision": a.precision, "machine": machine(),
            "blocks": a.blocks, "calls_per_block": per_block, "results": rows}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", default="1,10,32,100")
    ap.add_argument("--frames", type=int, default=600, help="timed calls per side")
    ap.add_argument("--precision", default="fp32", help="models of the plain run (--compare times fp32 and int8)")
    ap.add_argument("--compare", action="store_true", help="int8 vs fp32 and ONNX Runtime vs PyTorch eager, interleaved")
    ap.add_argument("--trackers", action="store_true", help="all seven extra IMUs against none, interleaved")
    ap.add_argument("--blocks", type=int, default=10, help="--compare/--trackers: blocks the timed calls are split into")
    ap.add_argument("--against", metavar="REV", help="another git revision's pipeline, interleaved with this tree's")
    ap.add_argument("--models-against", metavar="DIR", help="this tree's pipeline on DIR's models, interleaved with models/")
    ap.add_argument("--refine", action="store_true", help="a refinement step against an N=31 decoder call; the frame at K")
    ap.add_argument("--json")
    a = ap.parse_args()
    if (a.compare or a.trackers or a.against or a.models_against or a.refine) and not 1 <= a.blocks <= a.frames:
        ap.error("--blocks must be 1..--frames")
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    except (AttributeError, OSError):
        pass
    ns = [int(x) for x in a.samples.split(",")]
    if a.against or a.models_against:
        report = against(a, ns)
    else:
        take = from_sample(SAMPLE)
        frames = [take.signals.slice(t, t + 1) for t in range(take.frames)]
        report = (compare if a.compare else trackers if a.trackers else refine_bench if a.refine else plain)(a, frames, ns)
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
