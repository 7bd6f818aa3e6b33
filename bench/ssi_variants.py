"""SSI variants measured and not shipped (the SSI issue): how the sample set is drawn, and how a switch
weighs the foot slide it causes. Each runs edge eval at N=32 on an even spread of val clips.

    python bench/ssi_variants.py --data ../shared/mocap [--clips 60] [--out out/ssi_variants] [VARIANT ...]

Variants (default: all):
  base            the shipped pipeline (i.i.d. normal latents at the manifest's latent_scale, sample 0
                  at the prior mean)
  scale-1.5       latents drawn with 1.5x the prior's spread (scale-2 with 2x)
  orthogonal      latent directions orthonormal in blocks of the latent size, norms as drawn
  slide-cost-W    a criterion: W x the horizontal distance from each sample's ankles to the shown
                  sample's, weighted by the shown sample's foot-lock weights (a switch must pay for the
                  foot slide it causes)
  slide-choose-W  the same distance only where a switch chooses its target (the outlier test as shipped)
  kick-scale-S    the high-kick study (SSI Table 3) on the first 8 val clips with kicks, N=1/10/100,
                  latents at S x the prior's spread
  kick-oracle     on those clips at N=100 without SSI, at each apex: sample 0's distance to the target,
                  the closest sample's, and the highest sample toe against the truth's
Each variant is measured with and without SSI where that matters; N=1 on the same clips is the bar.
Prints one line per run and writes them as JSON. About 2 minutes on 2 cores for all.
"""
import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import motion.evaluate as ev
import edgetools.study as study
from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from edge.skeleton import ANKLES
from edge.ssi import is_outlier
from motion.takes import find_clips, load_take


def orthogonal_latents(rng, n, dim, norms):
    """n latent vectors whose directions are orthonormal within each block of `dim`, with the given norms."""
    blocks = [np.linalg.qr(rng.standard_normal((dim, dim)))[0].T for _ in range(-(-n // dim))]
    return np.concatenate(blocks)[:n] * norms[:, None]


class SlideCost:
    """W x the horizontal distance of each sample's ankles from the shown sample's, by its lock weights."""
    name = "slide"

    def __init__(self, pipe, weight):
        self.pipe, self.weight = pipe, weight

    def cost(self, ctx):
        return foot_slide(self.pipe, ctx.positions)


def foot_slide(pipe, positions):
    c = pipe.switcher.current
    ankles = positions[:, ANKLES][:, :, [0, 2]]
    return (np.linalg.norm(ankles - ankles[c], axis=-1) * pipe.feet.weight[c][None]).sum(-1)


def variant_pipeline(variant):
    """A Pipeline class with the variant's sample set or selection."""
    kind, _, arg = variant.rpartition("-")
    if not kind:                        # base, orthogonal, n1: no number
        kind, arg = variant, ""
    w = float(arg) if arg else 0.0

    class Variant(Pipeline):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            N, dim = self.latents.shape
            if N > 1 and kind in ("scale", "kick-scale"):
                self.latents[1:] *= w / self.latent_scale      # w x the prior's spread, whatever the manifest's
            elif N > 1 and kind == "orthogonal":
                rng = np.random.default_rng(k.get("seed", 0))
                self.latents[1:] = orthogonal_latents(rng, N - 1, dim, np.linalg.norm(self.latents[1:], axis=1))
            elif kind == "slide-cost":
                self.criteria.criteria.append(SlideCost(self, w))
            elif kind == "slide-choose":
                self.path.switch_to = self._choose_with_slide(w)
            self.decoder.latent[:N] = self.latents

        def _choose_with_slide(self, weight):
            def switch_to(s, N, c, margin):
                cost = self.buffer.cost[s, :N]
                if not is_outlier(cost, c, margin):
                    return -1
                total = cost + weight * foot_slide(self, self.bufs.pos[:N])
                total[c] = np.inf
                return int(np.argmin(total))
            return switch_to
    return Variant


def kick_oracle(data, clips=8, n=100):
    """What selection could reach on the high-kick study at most: every sample's toe at each apex."""
    takes = []
    for f in find_clips([data], "val"):
        take = load_take(f)
        if study.kick_apexes(take.gt_pos, "high-kick"):
            takes.append(take)
        if len(takes) >= clips:
            break
    first, best, highest, truth = [], [], [], []
    for take in takes:
        run = ev.run_take(Pipeline(PipelineOptions(samples=n, seed=0, ssi=False)), take, keep_samples=True)
        for f, j in study.kick_apexes(take.gt_pos, "high-kick"):
            d = np.linalg.norm(run.samples[f][:, j] - take.gt_pos[f, j], axis=-1)
            first.append(d[0]), best.append(d.min())
            highest.append(run.samples[f][:, j, 1].max()), truth.append(take.gt_pos[f, j, 1])
    return {"variant": "kick-oracle", "events": len(first), "sample0_m": round(float(np.mean(first)), 3),
            f"best_of_{n}_m": round(float(np.mean(best)), 3), "highest_sample_toe_m": round(float(np.mean(highest)), 2),
            "true_toe_m": round(float(np.mean(truth)), 2)}


def _run(job):
    variant, ssi, data, clips = job
    if variant == "kick-oracle":
        return kick_oracle(data)
    # edge eval and the study build their own Pipeline: the variant's class stands in for it, in this
    # worker process only (the variants are measurements, not runtime options)
    cls = variant_pipeline(variant)
    if variant.startswith("kick"):
        study.Pipeline = cls
        r = study.run_study([data], "high-kick", [1, 10, 100], 1, "val", max_clips=8, log=lambda *a: None)
        return {"variant": variant, "high_kick_m": {x["samples"]: round(x["mean"], 3) for x in r["results"]}}
    ev.Pipeline = cls
    samples = 1 if variant == "n1" else 32
    r = ev.evaluate([data], PipelineOptions(samples=samples, ssi=ssi), split="val", max_clips=clips, log=lambda *a: None)
    d = r["diversity"]
    return {"variant": variant, "samples": samples, "ssi": r["ssi"], "mpjpe_cm": round(r["mpjpe_cm"], 3),
            "foot_skate_cm_s": round(r["foot_skate_cm_s"], 2), "switches": r["ssi_switches"],
            "physical_sum": round(r["penetration_rate"] + r["leg_intersect_rate"] + r["float_rate"], 5),
            **({"oracle_lower_cm": round(d["oracle_lower_cm"], 2), "average_sample_lower_cm": round(d["average_sample_lower_cm"], 2),
                "oracle_to_average_lower": round(d["oracle_to_average_lower"], 3)} if d else {})}


VARIANTS = ["base", "scale-1.5", "scale-2", "orthogonal", "slide-cost-2", "slide-cost-6", "slide-choose-2",
            "slide-choose-8", "kick-scale-1", "kick-scale-3", "kick-oracle"]
DIVERSITY = ("base", "scale-1.5", "scale-2", "orthogonal")     # also measured without SSI


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("variants", nargs="*", default=VARIANTS)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--clips", type=int, default=60, help="an even spread of this many val clips")
    ap.add_argument("--out", default="out/ssi_variants")
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args()
    jobs = [("n1", False, a.data, a.clips)]
    for v in a.variants:
        jobs.append((v, True, a.data, a.clips))
        if v in DIVERSITY:
            jobs.append((v, False, a.data, a.clips))
    rows = []
    with ProcessPoolExecutor(a.jobs) as ex:
        for row in ex.map(_run, jobs):
            print(json.dumps(row), flush=True)
            rows.append(row)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ssi_variants.json").write_text(json.dumps({"clips": a.clips, "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
