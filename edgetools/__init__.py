"""The tools above the board runtime and the bridge: evaluation (`edge eval`), the SSI study,
profiling, the device simulator and replay, the host-side pose listener, and the bundled sample's
maker. The motion data they read (BVH, retargeting, takes, synthesised signals, metrics) is the
`motion` package below; the `edge` command that dispatches to them is `edgecli` above."""
