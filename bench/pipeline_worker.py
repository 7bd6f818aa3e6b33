"""One side of `bench/pipeline.py --against`: a pipeline of whichever tree is first on PYTHONPATH, timed
on request, so two revisions' code can be timed in turns from one parent process.

    PYTHONPATH=TREE python bench/pipeline_worker.py N PRECISION SAMPLE.npz WARMUP [MODELS]

Builds Pipeline(samples=N, precision=PRECISION) (on the models in MODELS when given) fed SAMPLE's frames, warms it with WARMUP frames and
prints {"rows": ...}; then each stdin line 'pipeline K' or 'decoder K' times K pipeline steps (the
frames going on where the last block stopped) or K bare decoder calls, and answers with their
durations in microseconds as one JSON line. Imports only what both old and new trees have (back to
e598c25).
"""
import json
import sys


def main():
    n, precision, sample, warmup = int(sys.argv[1]), sys.argv[2], sys.argv[3], int(sys.argv[4])
    models = sys.argv[5] if len(sys.argv) > 5 else None
    from edge.pipeline import Pipeline
    from edge.timing import time_calls      # in every revision since the compiled core (e598c25)
    try:
        from edgetools.takes import from_sample
    except ImportError:             # revisions before the tools moved out of edge/
        from edge.takes import from_sample
    take = from_sample(sample)
    frames = [take.signals.slice(t, t + 1) for t in range(take.frames)]
    pipe = Pipeline(samples=n, precision=precision) if models is None else \
        Pipeline(models=models, samples=n, precision=precision)
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
        print(json.dumps(us.tolist()), flush=True)


if __name__ == "__main__":
    main()
