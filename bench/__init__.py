"""Benchmarks, each run as a script (python bench/NAME.py; see bench/README or each header). A package only
so that the layer contract in pyproject.toml covers what they import: they sit on top, beside the `edge`
command."""
