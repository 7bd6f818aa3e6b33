"""The host side of scripts/arm64-insns (bench/arm64/frame_insns.py --report): the plugin's marks are
turned into per-tick instruction counts (the marks' own cost taken off), and the counts into each
board's tick time and the N it holds. The counting itself needs QEMU and root (not here); these pin
the arithmetic the per-board table in docs/deploying.md rests on."""
import json

import numpy as np
import pytest

from bench.arm64 import frame_insns as fi

MARK = 1_000           # the marks' own instructions, as the plugin sees them


def write_counts(folder, cpu, ticks):
    """A plugin output and a guest plan for `cpu`: ticks = {(N, K): instructions of every tick}."""
    plan, lines = [], ["1 0"] * 3 + [f"2 {MARK}"] * 3
    for run, ((n, k), per_tick) in enumerate(sorted(ticks.items()), start=1):
        base = run * 1_000_000
        for i, insns in enumerate(per_tick):
            lines += [f"{base + 2 * i} 0", f"{base + 2 * i + 1} {int(insns) + MARK}"]
            lines += [f"{base + fi.DECODER + 2 * i} 0", f"{base + fi.DECODER + 2 * i + 1} {int(insns) // 4 + MARK}"]
        plan.append({"run": run, "samples": n, "refine_steps": k, "precision": "int8", "native": True,
                     "frames": len(per_tick), "refined_frames": len(per_tick) if k else 0})
    (folder / f"insns-{cpu}.txt").write_text("\n".join(lines + ["total 123"]) + "\n")
    (folder / f"plan-{cpu}.json").write_text("some guest output\n" + json.dumps({"plan": plan}) + "\n")


def ticks_linear_in_n(base, per_sample, frames=20):
    """Every (N, K) tick: base + per_sample * N instructions, K=1 costing 2 M more, with a 10 % outlier
    tail so p90 and p50 differ."""
    out = {}
    for n in (1, 8, 16, 32):
        for k in (0, 1):
            cost = base + per_sample * n + 2e6 * k
            out[(n, k)] = [cost] * (frames - 2) + [cost * 1.5] * 2
    return out


def test_the_marks_own_cost_is_taken_off_each_tick(tmp_path):
    write_counts(tmp_path, "cortex-a76", ticks_linear_in_n(1e6, 1e5))
    plan = json.loads((tmp_path / "plan-cortex-a76.json").read_text().splitlines()[-1])["plan"]
    per_k, mark_cost = fi.frame_instructions(fi.read_counts(tmp_path / "insns-cortex-a76.txt"), plan)
    assert mark_cost == MARK
    assert np.median(per_k[0][1]["frame"]) == 1e6 + 1e5
    assert np.median(per_k[1][32]["frame"]) == 1e6 + 32 * 1e5 + 2e6
    assert np.median(per_k[1][32]["decoder"]) == int(1e6 + 32 * 1e5 + 2e6) // 4


def test_the_n_a_board_holds_is_where_its_p90_tick_crosses_the_budget():
    # 20 ticks, three of them 3x the rest: the p90 tick is a slow one (the median would hold more N).
    per_n = {n: {"frame": np.array([1e6 * n] * 17 + [3e6 * n] * 3)} for n in (1, 8, 16, 32)}
    p90 = {n: np.percentile(per_n[n]["frame"], 90) for n in per_n}
    # A budget that N=8 meets exactly and N=16 exceeds: interpolated between them.
    insns_per_ms = p90[8] / fi.BUDGET_MS
    assert fi.largest_n(per_n, insns_per_ms) == 8
    assert fi.largest_n(per_n, (p90[8] + p90[16]) / 2 / fi.BUDGET_MS) == 12
    assert fi.largest_n(per_n, p90[32] / fi.BUDGET_MS * 2) == 32        # all fit: the largest counted
    assert fi.largest_n(per_n, p90[1] / fi.BUDGET_MS / 2) == 0          # not even N=1


@pytest.mark.parametrize("per_sample, pi5", [(1e5, "32+"), (2e6, "5-8"), (2e7, "none")])
def test_the_report_gives_each_board_its_tick_time_and_n(tmp_path, per_sample, pi5):
    write_counts(tmp_path, "cortex-a72", ticks_linear_in_n(1e6, per_sample))
    write_counts(tmp_path, "cortex-a76", ticks_linear_in_n(1e6, per_sample))
    fi.report(tmp_path)
    result = json.loads((tmp_path / "report.json").read_text())
    boards = {b["board"]: b for b in result["boards"]}
    assert set(boards) == {b[0] for b in fi.BOARDS}
    pi4 = boards["Raspberry Pi 4 Model B (2022 on), Pi 400"]
    # N=1 with a target: (1 M + per_sample + 2 M) * 1.05 instructions at 1.8 GHz and IPC 1.3 .. 0.9.
    p90 = (3e6 + per_sample) * 1.05
    assert pi4["tick_ms_p90_k1"]["1"] == pytest.approx([p90 / (1.3 * 1.8e6), p90 / (0.9 * 1.8e6)])
    table = (tmp_path / "report.md").read_text()
    row = next(line for line in table.splitlines() if line.startswith("| Raspberry Pi 5 |"))
    assert row.split("|")[-3].strip() == pi5
    # A slower core holds no more than a faster one.
    held = [boards[b[0]]["n_held_k1"][1] for b in fi.BOARDS]
    assert held[:3] == sorted(held[:3]) and held[3] <= held[4] <= held[5]
