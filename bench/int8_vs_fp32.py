"""int8 against fp32 on the validation split, through the whole runtime, on this CPU, in one run.

    python bench/int8_vs_fp32.py [--data ../shared/mocap] [--samples 1,32] [--models DIR] [--out out/int8_vs_fp32]

Runs edge eval on val at each N in int8 and in fp32 (two at a time), each with a dump, then compares:
mpjpe (int8 / fp32, the model card's line: within +2 %), foot skate, the physical sum, and the
plausibility verdicts frame by frame (the shown pose above or below the autoencoder's threshold, as
the eval counts it; the line: the same on >= 99 % of frames). Names the CPU and the precision the
int8 run actually used (the start-up self-check may turn int8 off). Evals already in --out are reused.
"""
import argparse
import json
import platform
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from edge.options import PipelineOptions
from bench.cached import run_cached


def verdicts(dump_a, dump_b):
    """Frames after each clip's warm-up, and how many of them both runs judged alike."""
    same = frames = 0
    for fa in sorted(Path(dump_a).glob("*.npz")):
        with np.load(fa) as a, np.load(Path(dump_b) / fa.name) as b:
            w = int(a["warmup_frames"])
            va, vb = a["implausible"][w:], b["implausible"][w:]
            same += int(np.sum(va == vb))
            frames += len(va)
    return same, frames


def cpu_name():
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                flags = next((ln for ln in open("/proc/cpuinfo") if ln.startswith("flags")), "").split()
                isa = [f for f in ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "asimddp", "i8mm") if f in flags]
                return f"{line.split(':', 1)[1].strip()} ({', '.join(isa) or 'no avx2'})"
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--samples", default="1,32")
    ap.add_argument("--models", default=None)
    ap.add_argument("--out", default="out/int8_vs_fp32")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--max-clips", type=int, default=None, help="an even spread of this many val clips (a quick look)")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    ns = [int(n) for n in a.samples.split(",")]
    jobs = {(n, p): (str(out / f"n{n}_{p}.json"), {"data": a.data, "options": PipelineOptions(samples=n, precision=p),
                                                    "models": a.models, "dump": str(out / f"n{n}_{p}"), "max_clips": a.max_clips})
            for n in ns for p in ("int8", "fp32")}
    with ProcessPoolExecutor(a.jobs) as ex:
        res = dict(zip(jobs, ex.map(run_cached, jobs.values()), strict=True))
    print(f"val, int8 against fp32, CPU: {cpu_name()}")
    print(f"{'N':>4} {'mpjpe int8':>11} {'fp32':>8} {'ratio':>7} {'skate int8/fp32':>16} {'physical int8/fp32':>19} "
          f"{'verdicts same':>14}")
    table = []
    for n in ns:
        i8, f32 = res[n, "int8"], res[n, "fp32"]
        same, frames = verdicts(out / f"n{n}_int8", out / f"n{n}_fp32")
        row = {"samples": n, "mpjpe_int8_cm": i8["mpjpe_cm"], "mpjpe_fp32_cm": f32["mpjpe_cm"],
               "ratio": i8["mpjpe_cm"] / f32["mpjpe_cm"], "skate_int8": i8["foot_skate_cm_s"],
               "skate_fp32": f32["foot_skate_cm_s"], "physical_int8": i8["physical_sum"],
               "physical_fp32": f32["physical_sum"], "verdicts_same": same / frames, "frames": frames}
        row["int8_ran_as"] = i8.get("precision_in_use", "int8")
        table.append(row)
        print(f"{n:>4} {row['mpjpe_int8_cm']:>11.3f} {row['mpjpe_fp32_cm']:>8.3f} {row['ratio']:>7.4f} "
              f"{row['skate_int8']:>7.2f} / {row['skate_fp32']:<7.2f} {row['physical_int8']:>9.5f} / {row['physical_fp32']:<8.5f}"
              f" {100 * row['verdicts_same']:>12.2f} %")
    (out / "summary.json").write_text(json.dumps({"cpu": cpu_name(), "rows": table}, indent=2) + "\n")
    print(f"lines: mpjpe ratio <= 1.02, verdicts the same on >= 99 % of frames; wrote {out}/summary.json")


if __name__ == "__main__":
    main()
