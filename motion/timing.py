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


def time_alternating(calls, n):
    """Call each of calls {name: fn(i)} n times, taking turns call by call (A B A B ..., the first of
    each turn alternating), so a machine that slows down for a while slows every side alike. Returns
    {name: durations in microseconds [n]}."""
    names = list(calls)
    out = {k: np.empty(n) for k in names}
    for i in range(n):
        for k in (names if i % 2 == 0 else names[::-1]):
            t0 = time.perf_counter_ns()
            calls[k](i)
            out[k][i] = time.perf_counter_ns() - t0
    return {k: v / 1000.0 for k, v in out.items()}
