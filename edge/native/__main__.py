"""`python -m edge.native`: build the compiled core now (not at the service's first start) and say
whether the pipeline will use it. Exit status 1 when it cannot be built."""
import sys

from edge import native

lib = native.load()
if lib is None:
    print(f"compiled core unavailable: {native.why_unavailable()}; the pipeline will use numpy (slower)")
    sys.exit(1)
print(f"compiled core ready: {native.build()} ({native.build_flags() or 'flags unknown'})")
