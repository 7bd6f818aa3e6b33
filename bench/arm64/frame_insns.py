"""Guest side of the aarch64 instruction count (scripts/arm64-insns): run the board service's tick,
as `edge profile` runs it (sim:// sources -> sync -> calibration -> Pipeline.step -> POSE_FRAME
encoding; edgetools.profile.PacedRun), on the bundled walk at each N, and mark every tick for
bench/arm64/frame_insns.c, the QEMU plugin counting the instructions executed between marks.
Each N is counted twice: with no target (K = 0) and with a headset target live every frame refined
K = 1 step (the governor's rung for N <= 32 with refinement on; `edge profile`'s worst case).

    qemu-aarch64 -plugin frame_insns.so,out=FILE python bench/arm64/frame_insns.py [--samples 1,8,16,32]
    python bench/arm64/frame_insns.py --report out/arm64-insns     (on the host: the tables)

Marks, as ids (the plan the guest prints says which runs and how many frames the host should read):
    run*1_000_000 + 2*i       before tick i of run `run` (after the warm-up)
    run*1_000_000 + 2*i + 1   after it: the count at this id is tick i's instructions
    run*1_000_000 + 900_000 + 2*i (+1)   the same around the bare decoder call (the model alone)
    1 then 2                  two marks back to back: the marks' own cost, subtracted by the host
A mark is the syscall lseek(-1, id, "EPOS"), which fails harmlessly (EBADF) when nothing counts.
"""
import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent.parent))

WHENCE = 0x45504F53
DECODER = 900_000


def mark(marker_id):
    try:
        os.lseek(-1, marker_id, WHENCE)
    except OSError:
        pass


def count_frames(a):
    from edgetools.profile import PacedRun
    for _ in range(20):
        mark(1)
        mark(2)
    plan = []
    runs = [(int(n), k) for n in a.samples.split(",") for k in (0, 1)]
    for run_id, (n, k) in enumerate(runs, start=1):
        cfg = {"hz": 60.0, "precision": a.precision, "refine_steps": k}
        run = PacedRun(cfg, n, a.frames, adaptive=False, hog=None, steps=k)
        try:
            run.warm_up()                          # 60 ticks; a target goes live half way when K > 0
            base = run_id * 1_000_000
            for i in range(a.frames):
                mark(base + 2 * i)
                run.tick(run.WARM + i)
                mark(base + 2 * i + 1)
            for i in range(a.frames):
                mark(base + DECODER + 2 * i)
                run.pipe.decoder.step()
                mark(base + DECODER + 2 * i + 1)
            refined = (run.pipe.refiner.applied - run.refined_before) if run.pipe.refiner else 0
            plan.append({"run": run_id, "samples": n, "refine_steps": k, "precision": run.pipe.precision,
                         "native": run.pipe.native is not None, "frames": a.frames, "refined_frames": int(refined)})
        finally:
            run.close()
    print(json.dumps({"plan": plan}))


# ---------------------------------------------------------------- host side: counts -> frame time
# 60 Hz with a 25 % CPU share (the service's quota, docs/deploying.md section 5): 4.17 ms a frame.
BUDGET_MS = 1000.0 / 60.0 * 0.25
# (board, core, GHz, the QEMU model whose count it takes, assumed IPC low..high on this workload).
# The IPC ranges are assumptions, not measurements: a mix of CPython's interpreter loop (branchy,
# low IPC), numpy's small-array calls and onnxruntime's int8 GEMM kernels (high IPC). Published
# SPEC-int-like figures: in-order dual-issue A53 ~0.5-0.8, 3-wide out-of-order A72 ~0.9-1.3, 4-wide
# A76 ~1.5-2.2. Cortex-A53 runs ARMv8.0 like the A72, so it executes the A72 model's instructions.
BOARDS = (
    ("Raspberry Pi Zero 2 W", "Cortex-A53", 1.0, "cortex-a72", (0.5, 0.8)),
    ("Raspberry Pi 3 Model B", "Cortex-A53", 1.2, "cortex-a72", (0.5, 0.8)),
    ("Raspberry Pi 3 Model B+", "Cortex-A53", 1.4, "cortex-a72", (0.5, 0.8)),
    ("Raspberry Pi 4 Model B (early)", "Cortex-A72", 1.5, "cortex-a72", (0.9, 1.3)),
    ("Raspberry Pi 4 Model B (2022 on), Pi 400", "Cortex-A72", 1.8, "cortex-a72", (0.9, 1.3)),
    ("Raspberry Pi 5", "Cortex-A76", 2.4, "cortex-a76", (1.5, 2.2)),
)


def read_counts(path):
    """The plugin's "id instructions" lines -> {id: [counts]}."""
    counts = {}
    for line in Path(path).read_text().splitlines():
        key, value = line.split()
        if key != "total":
            counts.setdefault(int(key), []).append(int(value))
    return counts


def frame_instructions(counts, plan):
    """{K: {N: {"frame": each counted tick's instructions, "decoder": the bare decoder call's}}}, the
    marks' own cost taken off, and that cost."""
    mark_cost = float(np.median(counts[2]))
    out = {}
    for p in plan:
        base = p["run"] * 1_000_000
        frame = np.array([counts[base + 2 * i + 1][-1] for i in range(p["frames"])], float) - mark_cost
        dec = np.array([counts[base + DECODER + 2 * i + 1][-1] for i in range(p["frames"])], float) - mark_cost
        out.setdefault(p["refine_steps"], {})[p["samples"]] = {"frame": frame, "decoder": dec}
    return out, mark_cost


def largest_n(per_n, insns_per_ms):
    """The largest N (interpolated between the counted ones, linear in N) whose p90 tick fits the budget."""
    ns = sorted(per_n)
    cost = [np.percentile(per_n[n]["frame"], 90) / insns_per_ms for n in ns]
    if cost[0] > BUDGET_MS:
        return 0
    if cost[-1] <= BUDGET_MS:
        return ns[-1]
    return int(np.interp(BUDGET_MS, cost, ns))


def _held(per_n, ghz, ipcs):
    lo, hi = (largest_n(per_n, ipc * ghz * 1e6) for ipc in ipcs)
    top = max(per_n)
    text = "none" if hi == 0 else (f"{lo}" if lo == hi else f"{lo}-{hi}")
    return (text + "+" if hi == top else text), [lo, hi]


def report(folder):
    folder = Path(folder)
    result, lines, per_cpu = {"budget_ms": BUDGET_MS, "cpus": {}, "boards": []}, [], {}
    for counts_file in sorted(folder.glob("insns-*.txt")):
        cpu = counts_file.stem[len("insns-"):]
        plan = json.loads((folder / f"plan-{cpu}.json").read_text().strip().splitlines()[-1])["plan"]
        per_k, mark_cost = frame_instructions(read_counts(counts_file), plan)
        per_cpu[cpu] = per_k
        native = all(p["native"] for p in plan)
        result["cpus"][cpu] = {"mark_cost": mark_cost, "native": native, "precision": plan[0]["precision"],
                               "plan": plan, "ticks": {}}
        lines += [f"### Instructions per tick, QEMU {cpu} ({plan[0]['precision']}, compiled core: {native}; "
                  f"{plan[0]['frames']} ticks each, millions)", "",
                  "| N | tick, no target: p50 | p90 | tick, target refined (K=1): p50 | p90 | decoder call alone |",
                  "|---|---|---|---|---|---|"]
        for n in sorted(per_k[0]):
            a, b, dec = per_k[0][n]["frame"] / 1e6, per_k[1][n]["frame"] / 1e6, per_k[0][n]["decoder"] / 1e6
            result["cpus"][cpu]["ticks"][n] = {"k0_p50": float(np.median(a)), "k0_p90": float(np.percentile(a, 90)),
                                               "k1_p50": float(np.median(b)), "k1_p90": float(np.percentile(b, 90)),
                                               "decoder_p50": float(np.median(dec))}
            lines.append(f"| {n} | {np.median(a):.2f} | {np.percentile(a, 90):.2f} | {np.median(b):.2f} | "
                         f"{np.percentile(b, 90):.2f} | {np.median(dec):.2f} |")
        lines.append("")
    counted = sorted(next(iter(per_cpu.values()))[1]) if per_cpu else []
    lines += [f"### Estimated tick time, target refined (p90 tick; budget {BUDGET_MS:.2f} ms = 60 Hz at a 25 % CPU share)", "",
              "| board | core, clock | assumed IPC | " + " | ".join(f"N={n}" for n in counted)
              + " | N it holds: target refined | no target |", "|---" * (len(counted) + 5) + "|"]
    for board, core, ghz, model, ipcs in BOARDS:
        if model not in per_cpu:
            continue
        per_k = per_cpu[model]
        ms = {n: [np.percentile(d["frame"], 90) / (ipc * ghz * 1e6) for ipc in ipcs[::-1]] for n, d in per_k[1].items()}
        cells = [f"{ms[n][0]:.1f}-{ms[n][1]:.1f} ms" if n in ms else "-" for n in counted]
        held1, n1 = _held(per_k[1], ghz, ipcs)
        held0, n0 = _held(per_k[0], ghz, ipcs)
        lines.append(f"| {board} | {core} {ghz} GHz | {ipcs[0]}-{ipcs[1]} | " + " | ".join(cells) + f" | {held1} | {held0} |")
        result["boards"].append({"board": board, "core": core, "ghz": ghz, "model": model, "ipc": list(ipcs),
                                 "tick_ms_p90_k1": ms, "n_held_k1": n1, "n_held_k0": n0})
    lines += ["", "(N+: the largest N counted fits, and the board may hold more. 0: not even N=1 fits with a "
              "refinement step; the governor then runs N=1 without refining, K=0.)"]
    text = "\n".join(lines) + "\n"
    (folder / "report.md").write_text(text)
    (folder / "report.json").write_text(json.dumps(result, indent=2, default=float) + "\n")
    print(text)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", default="1,8,16,32")
    ap.add_argument("--frames", type=int, default=100, help="counted ticks per run")
    ap.add_argument("--precision", default="int8")
    ap.add_argument("--report", metavar="FOLDER", help="on the host: read FOLDER's counts and print the tables")
    a = ap.parse_args()
    if a.report:
        report(a.report)
    else:
        count_frames(a)


if __name__ == "__main__":
    main()
