"""Training windows made on the accelerator (models.batches) are the numpy reference's
(motion.dataset.make_batch): one draw of random numbers rendered both ways gives the same inputs and
targets, and torch's draws have the reference's distributions. Needs torch and ../shared/mocap."""
import numpy as np
import pytest

from motion import dataset as ds
from motion.synth import DeviceNoise
from edge.imus import ImuNoise


@pytest.fixture(scope="module")
def val(mocap):
    return ds.build(mocap, "val")


@pytest.mark.parametrize("with_imus", [True, False])
def test_the_device_renders_the_windows_numpy_renders_from_the_same_numbers(torch, val, with_imus):
    from models.batches import DeviceBatches
    rng = np.random.default_rng(3)
    d = ds.draw_batch(rng, rng.choice(ds.window_starts(val, 60), 48), 60, DeviceNoise(), ImuNoise(), with_imus)
    want = ds.render_batch(val, d, 60, DeviceNoise(), ImuNoise())
    got = DeviceBatches(val, 60, "cpu", dtype=torch.float64).render(d)
    assert set(got) == set(want)
    for k in want:
        assert tuple(got[k].shape) == want[k].shape, k
        # float32 outputs: velocities (x 60 Hz) to 1e-4, positions and rotations to 1e-6
        np.testing.assert_allclose(got[k].numpy(), want[k], atol=1e-4 if k == "features" else 1e-6, err_msg=k)


@pytest.mark.parametrize("speed", [False, True])
def test_the_device_mirrors_and_retimes_windows_as_numpy_does(torch, val, speed):
    from models.batches import DeviceBatches
    rng = np.random.default_rng(4)
    d = ds.draw_batch(rng, rng.choice(ds.window_starts(val, 80), 32), 60, DeviceNoise(), ImuNoise())
    d["mirror"] = rng.random(32) < 0.5
    if speed:
        d["speed"] = rng.uniform(0.8, 1.25, 32)
    want = ds.render_batch(val, d, 60, DeviceNoise(), ImuNoise())
    got = DeviceBatches(val, 60, "cpu", dtype=torch.float64).render(d)
    for k in want:
        np.testing.assert_allclose(got[k].numpy(), want[k], atol=1e-4 if k == "features" else 1e-6, err_msg=k)


def test_the_device_draws_windows_by_person_as_the_rule_says(torch):
    from models.batches import DeviceBatches
    from tests.test_augment import people_set
    cs = people_set()
    dev = DeviceBatches(cs, 60, "cpu", seed=2, windows_by="people")
    starts = dev.draw(20000, with_imus=False)["starts"].numpy()
    share = np.bincount(np.searchsorted(cs.starts, starts, side="right") - 1, minlength=3) / len(starts)
    np.testing.assert_allclose(share, [0.2, 0.2, 0.6], atol=0.015)


def test_the_devices_random_numbers_have_the_references_distributions(torch, val):
    from models.batches import DeviceBatches
    B = 4096
    dev = DeviceBatches(val, 60, "cpu", seed=1).draw(B)
    ref = ds.draw_batch(np.random.default_rng(1), np.zeros(B, int), 60, DeviceNoise(), ImuNoise())
    for group in ("device", "imu"):
        for k, want in ref[group].items():
            got = dev[group][k].numpy()
            assert got.shape == want.shape, (group, k)
            assert got.mean() == pytest.approx(want.mean(), abs=0.05 * want.std() + 0.02), (group, k)
            assert got.std() == pytest.approx(want.std(), rel=0.05), (group, k)
    assert dev["yaw"].std().item() == pytest.approx(ref["yaw"].std(), rel=0.05)
    worn, alive = dev["worn"].numpy() > 0, dev["alive"].numpy()
    assert (~worn.any(1)).mean() == pytest.approx((~ref["worn"].astype(bool).any(1)).mean(), abs=0.03)
    assert worn.mean() == pytest.approx(ref["worn"].mean(), abs=0.03)
    assert alive[:, worn].mean() == pytest.approx(ref["alive"][:, ref["worn"] > 0].mean(), abs=0.03)
    assert dev["starts"].min() >= 0 and dev["starts"].max() <= ds.window_starts(val, 60).max()
