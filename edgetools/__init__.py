"""The tools above the board runtime and the bridge: the `edge` command (cli), evaluation, the SSI
study, profiling, the device simulator and replay, the host-side pose listener, and the motion data
they read (BVH, retargeting, takes, synthesised signals)."""
