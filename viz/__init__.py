"""Pictures of what edgepose tracked: reports, plots, skeleton renders and a live view.

    edge report RUN.json --dump DIR --out DIR     # viz.report: PNGs, a GIF and an index.html
    edge eval ... --report DIR                    # the same, straight after an evaluation
    edge listen PORT --plot                       # viz.live: a live 3D stick figure of the stream

Modules, top to bottom:

- `canvas`: the one place that imports matplotlib (Agg, no pyplot) and turns figures into pixels.
- `skeleton_draw`: body-facing front and side projections of joint positions and drawing them.
- `figures`: one function per picture (skeleton strip, per-joint errors, latency, SSI, tracker health).
- `animation`: the ground-truth-beside-prediction GIF.
- `report`: reads an `edge eval` JSON and dump folder, draws what the data allows, writes index.html.
- `live`: the desktop window for `edge listen --plot`.

The plotting libraries (matplotlib, pillow) are the optional `[viz]` extra. They are imported lazily,
inside the functions that draw, so `import viz` is cheap and the board runtime (`edge/`,
`firmware_bridge/`) never loads them.
"""
