"""One side of `bench/pipeline.py --against`: a pipeline of whichever tree is first on PYTHONPATH, timed
on request, so two revisions' code can be timed in turns from one parent process.

    PYTHONPATH=TREE python bench/pipeline_worker.py N PRECISION SAMPLE.npz WARMUP [MODELS]

Builds a Pipeline of N samples at PRECISION (on the models in MODELS when given) fed SAMPLE's frames, warms it with WARMUP frames and
prints {"rows": ...}; then each stdin line 'pipeline K' or 'decoder K' times K pipeline steps (the
frames going on where the last block stopped) or K bare decoder calls, and answers with their
durations in microseconds as one JSON line. Imports only what both old and new trees have (back to
e598c25).
"""
import importlib
import json
import sys
import time


def time_calls(fn, n):
    """Call fn(i) for i in range(n); each call's duration in microseconds (the same loop for both trees)."""
    out = []
    for i in range(n):
        t0 = time.perf_counter_ns()
        fn(i)
        out.append((time.perf_counter_ns() - t0) / 1000.0)
    return out


def _import_from_sample():
    """motion.takes.from_sample, wherever the tree on PYTHONPATH keeps it."""
    for module in ("motion.takes", "edgetools.takes", "edge.takes"):   # newest first: the tools moved twice
        try:
            return importlib.import_module(module).from_sample
        except ImportError:
            continue
    raise ImportError("no takes module (motion.takes, edgetools.takes or edge.takes) on PYTHONPATH")


def _pipeline(Pipeline, n, precision, models):
    """Pipeline(PipelineOptions(samples=n, precision=...), models), or the keywords of trees before
    edge.options."""
    try:
        from edge.options import PipelineOptions
    except ImportError:
        return Pipeline(models=models, samples=n, precision=precision)
    return Pipeline(PipelineOptions(samples=n, precision=precision), models=models)


def main():
    n, precision, sample, warmup = int(sys.argv[1]), sys.argv[2], sys.argv[3], int(sys.argv[4])
    models = sys.argv[5] if len(sys.argv) > 5 else None
    from edge.pipeline import Pipeline
    from_sample = _import_from_sample()
    take = from_sample(sample)
    frames = [take.signals.slice(t, t + 1) for t in range(take.frames)]
    pipe = _pipeline(Pipeline, n, precision, models)
    for t in range(warmup):
        pipe.step(frames[t % len(frames)])
    t = warmup
    print(json.dumps({"rows": pipe.decoder.rows}), flush=True)
    for line in sys.stdin:
        what, k = line.split()
        k = int(k)
        if what == "pipeline":
            us = time_calls(lambda i, t0=t: pipe.step(frames[(t0 + i) % len(frames)]), k)
            t += k
        else:
            us = time_calls(lambda i: pipe.decoder.step(), k)
        print(json.dumps(us), flush=True)


if __name__ == "__main__":
    main()
