"""The training pack and the accelerator run's script, on CPU at a tiny size, so that the one real run
on a lent machine is not spent on a typo: a pack of a few real clips holds the frames training reads
(30 and 24 fps clips made again from their own frames), and scripts/train-device trains two widths side by
side from it, writes what comes back from the device tool (a tar per width and one to resume from) and
continues from those. Needs torch and ../shared/mocap."""
import csv
import os
import subprocess
import sys
import tarfile

import numpy as np
import pytest

from tests.conftest import ROOT

# a 30 fps Bandai clip, a 60 fps CMU one and a 24 fps one of the CMU library (data v4) for train, one of
# the first two kinds for val (all over 4 s: the validation windows are 240 frames)
CLIPS = {"train": ["bandai_namco_ccbync/dataset-1/dataset-1_bye_feminine_001.bvh", "cmu_amc2bvh/02/02_01.bvh",
                   "cmu_fbx_daz/140/140_04.bvh"],
         "val": ["bandai_namco_ccbync/dataset-2/dataset-2_walk_elderly_004.bvh", "cmu_amc2bvh/09/09_12.bvh"]}


@pytest.fixture(scope="module")
def tiny_mocap(mocap, tmp_path_factory):
    """A mocap folder of four real clips (links to ../shared/mocap) with its own MANIFEST.tsv."""
    root = tmp_path_factory.mktemp("mocap")
    with open(mocap / "MANIFEST.tsv", newline="") as f:
        rows = {r["file"]: r for r in csv.DictReader(f, delimiter="\t")}
    keep = [dict(rows[c], split=split) for split, clips in CLIPS.items() for c in clips]
    with open(root / "MANIFEST.tsv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(keep[0]), delimiter="\t")
        w.writeheader()
        w.writerows(keep)
    for r in keep:
        (root / r["file"]).parent.mkdir(parents=True, exist_ok=True)
        os.symlink(mocap / r["file"], root / r["file"])
    return root


@pytest.fixture(scope="module")
def tiny_pack(tiny_mocap, tmp_path_factory):
    from motion.pack import build_pack
    out = tmp_path_factory.mktemp("pack") / "pack.npz"
    info = build_pack(tiny_mocap, out)
    return out, info


def test_the_pack_holds_the_frames_training_reads(tiny_mocap, tiny_pack):
    from motion.pack import read_clips
    path, info = tiny_pack
    assert info["splits"]["train"]["stored_frames"] < info["splits"]["train"]["frames_60hz"]   # 30 fps kept as 30
    # 140_04 is the clip whose 24 fps frames the first v4 pack kept as if they were 30 fps (294 mm off)
    assert info["error_mm"]["train"]["max"] < 1.0 and info["error_mm"]["val"]["max"] < 1.0
    for split in ("train", "val"):
        want, got = read_clips(tiny_mocap, split), read_clips(path, split)
        assert np.array_equal(want.starts, got.starts) and np.array_equal(want.contacts, got.contacts)
        # every quaternion to Q13 rounding (the interpolated 24 and 30 fps frames included), every root to 0.1 mm
        dots = np.abs(np.sum(want.rotations.astype(np.float64) * got.rotations, axis=-1))
        assert np.degrees(2 * np.arccos(np.clip(dots, -1, 1))).max() < 0.05
        assert np.abs(want.root - got.root).max() < 1e-4
    only_cmu = read_clips(path, "train", ["cmu"])
    assert [n.split("/")[0] for n in only_cmu.names] == ["cmu_amc2bvh"]
    assert [n.split("/")[0] for n in read_clips(path, "train", ["daz"]).names] == ["cmu_fbx_daz"]
    assert [n.split("/")[0] for n in read_clips(path, "train", ["cmu_fbx_daz"]).names] == ["cmu_fbx_daz"]


def test_the_clips_with_their_sources_conventions_left_in_are_read_beside_the_others(tiny_mocap, tiny_pack, tmp_path):
    from motion import dataset as ds
    from motion.pack import PackError, read_clips
    from motion.retarget import load_motion
    kept = ds.build(tiny_mocap, "val", cache_dir=tmp_path, conventions=False)
    taken_out = ds.build(tiny_mocap, "val", cache_dir=tmp_path)
    assert len(list(tmp_path.glob("clips-val-*.npz"))) == 2        # two caches, never one for both
    assert kept.names == taken_out.names and not np.allclose(kept.rotations, taken_out.rotations, atol=1e-3)
    first = load_motion(kept.names[0], ds.FPS, conventions=False)
    assert np.array_equal(kept.rotations[:len(first.rotations)], first.rotations.astype(np.float32))
    with pytest.raises(PackError, match="read the mocap folder"):
        read_clips(tiny_pack[0], "train", conventions=False)


def test_train_device_trains_two_widths_and_resumes_from_what_it_brought_back(torch, tiny_pack, tmp_path):
    pack, _ = tiny_pack
    env = dict(os.environ, PYTHON=sys.executable, OUT=str(tmp_path / "run1"))
    tiny = ["--", "--batch", "4", "--steps", "3", "--val-every", "2", "--val-windows", "2", "--ae-steps", "2"]
    cmd = [str(ROOT / "scripts" / "train-device"), "--device", "cpu", "--sizes", "16,24", "--pack", str(pack)]
    # the first run also trains a model on the sources without a non-commercial term, beside them
    r = subprocess.run(cmd + ["--cmu-width", "16"] + tiny, env=env, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    with tarfile.open(tmp_path / "run1" / "h16-cmu.tar") as tar:
        import json
        meta = json.load(tar.extractfile("meta.json"))
        assert meta["sources"] == ["cmu", "daz", "hdm05"] and "bandai" not in meta["licences"]
        assert "ae.pt" in tar.getnames()
    resume = tmp_path / "resume"
    for h in (16, 24):
        for name, members in ((f"h{h}.tar", {"cvae.pt", "ae.pt", "meta.json", "train_log.txt"}),
                              (f"h{h}-resume.tar", {"cvae_last.pt", "train_state.pt"})):
            with tarfile.open(tmp_path / "run1" / name) as tar:
                assert set(tar.getnames()) == members
                tar.extractall(resume / f"h{h}", filter="data")
        state = torch.load(resume / f"h{h}" / "cvae.pt", weights_only=True)
        assert state["dec_gru.weight_hh_l0"].shape == (3 * h, h)
    env["OUT"] = str(tmp_path / "run2")       # the second run makes its windows the accelerator's way
    resume_one = [c if c != "16,24" else "24" for c in cmd]          # one width resumed is the proof (CI's time)
    r = subprocess.run(resume_one + ["--resume", str(resume)] + tiny + ["--batches", "device"], env=env,
                       capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "resumed from" in r.stdout and "after 3 steps" in r.stdout
    assert "made on cpu (models.batches)" in r.stdout and "windows a minute" in r.stdout
    with tarfile.open(tmp_path / "run2" / "h24.tar") as tar:
        meta = json.load(tar.extractfile("meta.json"))
    assert meta["iterations"] == 6 and meta["hidden"] == 24 and meta["data_sha256"]
