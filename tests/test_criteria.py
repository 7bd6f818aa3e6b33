"""SSI selection criteria and the outlier rule."""
import numpy as np

from edge import quat
from edge.criteria import CollisionAvoid, Composite, FrameContext, SensorAgreement, TargetHit
from edge.ssi import best_other, is_outlier
from edge.skeleton import JOINT, NUM_JOINTS


def ctx_with(positions, world_rot=None, imu=None):
    N = len(positions)
    if world_rot is None:
        world_rot = np.broadcast_to(np.eye(3), (N, NUM_JOINTS, 3, 3)).copy()
    return FrameContext(0, positions, world_rot, world_rot[:, 0], imu or {})


def test_outlier_rule_flags_a_clear_outlier_only():
    cost = np.array([1.0, 1.1, 1.2, 1.15, 3.0])
    assert is_outlier(cost, 4)
    assert not is_outlier(cost, 1)
    assert best_other(cost, 4) == 0 and best_other(cost, 0) == 1
    assert cost[0] == 1.0  # untouched


def test_target_hit_prefers_the_sample_whose_foot_is_at_the_target():
    pos = np.zeros((3, NUM_JOINTS, 3))
    pos[:, JOINT["r_toe"]] = [[0, 0.2, 0], [0, 1.0, 0.3], [0, 0.5, 0.1]]
    crit = TargetHit("r_toe", lambda f: np.array([0, 1.0, 0.3]))
    assert np.argmin(crit.cost(ctx_with(pos))) == 1
    idle = TargetHit("r_toe", lambda f: None)
    assert np.all(idle.cost(ctx_with(pos)) == 0)


def test_collision_cost_is_penetration_depth():
    pos = np.zeros((2, NUM_JOINTS, 3)) + 5.0
    pos[0, JOINT["l_knee"]] = [0, 0.5, 0.05]   # 5 cm inside a 10 cm ball at (0, 0.5, 0)
    crit = CollisionAvoid([[0, 0.5, 0]], [0.1])
    assert np.allclose(crit.cost(ctx_with(pos)), [0.05, 0.0])


def test_sensor_agreement_is_zero_when_orientations_match_and_grows_with_error():
    N = 3
    rot = np.broadcast_to(np.eye(3), (N, NUM_JOINTS, 3, 3)).copy()
    for i, deg in enumerate([0, 10, 40]):
        rot[i, JOINT["l_ankle"]] = quat.to_matrix(quat.from_axis_angle(np.array([1.0, 0, 0]), np.radians(deg)))
    cost = SensorAgreement().cost(ctx_with(np.zeros((N, NUM_JOINTS, 3)), rot, {JOINT["l_ankle"]: np.eye(3)}))
    assert np.allclose(np.degrees(cost), [0, 10, 40])


def test_composite_weights_add_up():
    pos = np.zeros((2, NUM_JOINTS, 3))
    pos[1, JOINT["r_toe"]] = [1.0, 0, 0]
    a = TargetHit("r_toe", lambda f: np.zeros(3), weight=2.0)
    b = TargetHit("r_toe", lambda f: np.zeros(3), weight=0.5)
    assert np.allclose(Composite([a, b]).cost(ctx_with(pos)), [0, 2.5])


def test_ssi_samples_are_drawn_at_the_manifests_latent_scale_and_a_bad_one_is_refused():
    """The samples' latents are the prior's draws at the manifest's latent_scale (0.7 for v0.3), sample 0
    stays the prior mean, an explicit selection's scale wins, and a scale that is not a number in
    (0, 4] fails at start-up with the fix."""
    import pytest
    from edge.modelfiles import ModelError, load_manifest
    from edge.options import PipelineOptions
    from edge.pipeline import Pipeline
    scale = load_manifest(need=())["selection"]["latent_scale"]
    draws = np.random.default_rng(0).standard_normal((7, 30))
    pipe = Pipeline(PipelineOptions(samples=8, seed=0))
    assert scale == pipe.latent_scale != 1.0
    np.testing.assert_array_equal(pipe.latents[0], 0.0)
    np.testing.assert_allclose(pipe.latents[1:], scale * draws, rtol=1e-6)
    wide = Pipeline(PipelineOptions(samples=8, seed=0, selection={"plausibility": 1.0, "latent_scale": 1.0}))
    np.testing.assert_allclose(wide.latents[1:], draws, rtol=1e-6)
    for bad in (0.0, -1.0, 9.0, float("nan"), "0.7", True):
        with pytest.raises(ModelError, match="latent_scale"):
            Pipeline(PipelineOptions(samples=2, selection={"plausibility": 1.0, "latent_scale": bad}))
