"""Motion data and its measures, below the tools: what `models`, `quantize`, `edgetools` and `viz`
read motion through, importing none of them.

Modules, in the order data flows through them:

- `bvh`: BVH files parsed into joint trees and channels.
- `retarget`: any source skeleton onto edgepose's (edge.skeleton), at the model rate.
- `synth`: tracker signals from a pose sequence: head, hands, waist and worn IMUs with device noise.
- `takes`: a clip or a bundled sample as a Take (signals in, ground truth out), and finding clips.
- `contacts`: foot-contact labels from motion.
- `metrics`: accuracy, smoothness, physical and diversity measures (docs/metrics.md).
- `evaluate`: takes through the real per-frame pipeline, scored (the library behind `edge eval`).
- `dataset`, `pack`: the retargeted train and val clips as training reads them, cached or packed.
- `timing`: timing loops shared by the benchmarks and the int8 report.
"""
