"""One evaluation job, cached: the bench scripts run motion.evaluate (`edge eval`'s scoring) on val for
many settings, in a process pool, each into a JSON file of the output folder. A job whose file is
already there is read back instead of run again, so a script stopped half-way, or rerun to add a
setting, redoes only what is missing (delete the folder to measure again).

    with ProcessPoolExecutor(2) as ex:
        results = list(ex.map(run_cached, [(out / "n1.json", {"data": data, "options": options}), ...]))
"""
import json
from pathlib import Path

from motion.evaluate import evaluate


def run_cached(job):
    """job = (path, keyword arguments of motion.evaluate, with "data" (the mocap folder) and "options",
    and optionally keep_per_clip=True): the evaluation of val, read from `path` when it is there. A file
    from before val was split by people (no "people" entry) is run again, unless the job asks for one
    group of people, whose evaluation has no such entry."""
    path, kw = Path(job[0]), dict(job[1])
    keep_per_clip = kw.pop("keep_per_clip", False)
    if path.exists():
        r = json.loads(path.read_text())
        if "people" in r or kw.get("people"):
            return r
    r = evaluate([kw.pop("data")], kw.pop("options"), split="val", log=lambda *a: None, **kw)
    if not keep_per_clip:
        r.pop("per_clip", None)
    path.write_text(json.dumps(r, indent=2) + "\n")
    return r
