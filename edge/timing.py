"""Timing helper shared by the benchmarks and the quantization report."""
import time

import numpy as np


def time_calls(fn, n):
    """Call fn(i) for i in range(n); return each call's duration in microseconds [n]."""
    out = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter_ns()
        fn(i)
        out[i] = time.perf_counter_ns() - t0
    return out / 1000.0
