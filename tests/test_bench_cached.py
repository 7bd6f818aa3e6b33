"""bench/cached.py: each bench script's evaluation jobs run once; a job whose JSON is in the output folder
is read back, and one from before val was split by people is run again."""
import json

from bench import cached


def test_a_job_already_in_the_folder_is_read_back_and_an_old_one_run_again(tmp_path, monkeypatch):
    runs = []

    def fake_evaluate(paths, options, split, log, **kw):
        runs.append((tuple(paths), options, split, kw))
        return {"mpjpe_cm": 5.0, "people": {"unseen": {}}, "per_clip": [1, 2]}
    monkeypatch.setattr(cached, "evaluate", fake_evaluate)
    job = (tmp_path / "a.json", {"data": "DATA", "options": "OPTS", "trackers": ("l_shin",)})
    first = cached.run_cached(job)
    assert runs == [(("DATA",), "OPTS", "val", {"trackers": ("l_shin",)})] and "per_clip" not in first
    assert cached.run_cached(job) == first and len(runs) == 1                 # read back, not run again
    (tmp_path / "old.json").write_text(json.dumps({"mpjpe_cm": 9.0}))         # no people split
    assert cached.run_cached((tmp_path / "old.json", {"data": "DATA", "options": "OPTS"}))["mpjpe_cm"] == 5.0
    assert len(runs) == 2
    (tmp_path / "one.json").write_text(json.dumps({"mpjpe_cm": 7.0}))         # one group asked for: no split
    assert cached.run_cached((tmp_path / "one.json", {"data": "D", "options": "O", "people": "unseen"}))["mpjpe_cm"] == 7.0
    kept = cached.run_cached((tmp_path / "b.json", {"data": "D", "options": "O", "keep_per_clip": True}))
    assert kept["per_clip"] == [1, 2] and len(runs) == 3
