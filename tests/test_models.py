"""Shipped ONNX models: manifest checks and parity with the PyTorch networks they were exported from."""
import shutil

import numpy as np
import pytest

from edge.features import sequence_features
from edge.inference import Decoder
from edge.loading import load_models
from edge.modelfiles import DEFAULT_DIR, ModelError, load_manifest
from motion.takes import from_sample
from tests.conftest import SAMPLE


def test_manifest_matches_the_shipped_files():
    m = load_manifest()
    assert set(m["paths"]) == {"decoder.onnx", "autoencoder.onnx"}
    assert 0.0 < m["plausibility_threshold_m"] < 1.0


@pytest.fixture
def model_copy(tmp_path):
    for name in ("decoder.onnx", "autoencoder.onnx", "manifest.json"):
        shutil.copy(DEFAULT_DIR / name, tmp_path / name)
    return tmp_path


def test_corrupt_model_file_is_refused_with_a_clear_message(model_copy):
    data = bytearray((model_copy / "decoder.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (model_copy / "decoder.onnx").write_bytes(bytes(data))
    with pytest.raises(ModelError, match="corrupt or altered"):
        load_models(model_copy, precision="fp32")


def test_missing_model_file_is_refused_with_a_clear_message(model_copy):
    (model_copy / "autoencoder.onnx").unlink()
    with pytest.raises(ModelError, match="missing"):
        load_models(model_copy, precision="fp32")


def test_missing_manifest_says_how_to_make_one(tmp_path):
    with pytest.raises(ModelError, match="models.export"):
        load_models(tmp_path)


def test_model_that_is_not_onnx_fails_at_load(model_copy):
    from edge.modelfiles import write_manifest
    import json
    (model_copy / "decoder.onnx").write_bytes(b"not a model")
    info = json.loads((model_copy / "manifest.json").read_text())
    info.pop("files")
    write_manifest(model_copy, ["decoder.onnx", "autoencoder.onnx"], info)
    with pytest.raises(ModelError, match="cannot load model"):
        load_models(model_copy, precision="fp32")


def _sample_features(T=300):
    """The bundled walk's decoder input, as wide as the shipped decoder reads it; with the extra IMUs
    (when it reads them) worn on both legs and dropping out (edge.imus), so those inputs are exercised."""
    from edge.imus import IMU_LOCATIONS, ImuNoise, dragposer_drops, mask
    from motion.synth import wear
    take = from_sample(SAMPLE)
    rng = np.random.default_rng(0)
    worn = mask(IMU_LOCATIONS[1:5])
    sig = wear(take.signals, worn, take.fps, rng, ImuNoise(), dragposer_drops(rng, take.frames, worn, p=0.02, frames=40))
    f, _, _ = sequence_features(sig, take.fps, n_features=load_manifest()["features"])
    return f[:T].astype(np.float32)


def _torch_models(torch):
    from models.export import load_checkpoint
    cvae, ae, _ = load_checkpoint(DEFAULT_DIR / "checkpoints")
    return cvae, ae


def _upper_head(torch):
    from models.export import load_upper
    return load_upper(DEFAULT_DIR / "checkpoints")


def test_onnx_decoder_matches_pytorch_over_a_300_frame_closed_loop(torch):
    from models.nets import DecoderStep
    cvae, _ = _torch_models(torch)
    step = DecoderStep(cvae, _upper_head(torch)).eval()
    feats = _sample_features(300)
    n = 8
    m = load_manifest()
    from edge.inference import make_session
    dec = Decoder(make_session(m["paths"]["decoder.onnx"]), n, m["latent"], m["hidden"], m["features"])
    z = np.random.default_rng(0).standard_normal((n, m["latent"])).astype(np.float32)
    dec.latent[:] = z
    h = torch.zeros(n, m["hidden"])
    worst = 0.0
    with torch.no_grad():
        for t in range(len(feats)):
            x = torch.from_numpy(np.repeat(feats[t:t + 1], n, 0))
            rot, con, h = step(x, torch.from_numpy(z), h)
            dec.features[:] = feats[t]
            dec.step()
            worst = max(worst, np.abs(dec.rot6d - rot.numpy()).max(), np.abs(dec.contacts - con.numpy()).max(),
                        np.abs(dec.state - h.numpy()).max())
    assert worst < 1e-4


@pytest.mark.parametrize("file", ["decoder.onnx", "decoder.int8.onnx"])
def test_a_frames_rows_read_one_shared_row_of_features(file):
    """A frame's N rows share its features, so the pipeline's decoder binds one row of them and the graph
    broadcasts it (its first layer's feature part runs once a frame); the rows come out as from N copies.
    The other rows of the buffer are never read (NaN there would show)."""
    from edge.inference import make_session
    m = load_manifest()
    session = make_session(DEFAULT_DIR / file)
    n = 5
    shared = Decoder(session, n, m["latent"], m["hidden"], m["features"], shared_features=True)
    copies = Decoder(session, n, m["latent"], m["hidden"], m["features"])
    assert shared.shared_features and not copies.shared_features
    z = np.random.default_rng(1).standard_normal((n, m["latent"])).astype(np.float32)
    shared.latent[:], copies.latent[:] = z, z
    for f in _sample_features(30):
        shared.features[0], shared.features[1:] = f, np.nan
        copies.features[:] = f
        shared.step()
        copies.step()
        for a, b in ((shared.rot6d, copies.rot6d), (shared.contacts, copies.contacts), (shared.state, copies.state)):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


def test_the_bound_run_is_the_public_run_and_falls_back_to_it():
    """edge.inference.bound_run calls ONNX Runtime's C++ binding straight (skipping the Python wrapper's
    per-call checks): the decoder's ping-pong steps give what session.run_with_iobinding gives, and a
    session without the binding's internals gets the public call."""
    from edge.inference import bound_run, make_session
    m = load_manifest()
    session = make_session(DEFAULT_DIR / "decoder.int8.onnx")
    fast = Decoder(session, 3, m["latent"], m["hidden"], m["features"], shared_features=True)
    public = Decoder(session, 3, m["latent"], m["hidden"], m["features"], shared_features=True)
    public._run = [lambda io=io: session.run_with_iobinding(io) for io in public._io]
    z = np.random.default_rng(2).standard_normal((3, m["latent"])).astype(np.float32)
    fast.latent[:], public.latent[:] = z, z
    for f in _sample_features(8):
        fast.features[0] = public.features[0] = f
        fast.step()
        public.step()
        for a, b in ((fast.rot6d, public.rot6d), (fast.contacts, public.contacts), (fast.state, public.state)):
            np.testing.assert_array_equal(a, b)
    assert fast.state.any()

    class Wrapped:                  # another onnxruntime: a session object without `_sess`
        def __init__(self):
            self.calls = 0

        def run_with_iobinding(self, io, options=None):
            self.calls += 1
            session.run_with_iobinding(io, options)

    other = Wrapped()
    bound_run(other, fast._io[0])()
    assert other.calls == 1


def test_written_out_gru_cell_matches_torch_gru(torch):
    from models.nets import DecoderStep
    cvae, _ = _torch_models(torch)
    step = DecoderStep(cvae).eval()
    feats = torch.from_numpy(_sample_features(200)[:, :cvae.n_features])[:, None].repeat(1, 3, 1)
    z = torch.randn(1, 3, 30).repeat(200, 1, 1)
    with torch.no_grad():
        rot_seq, con_seq, _ = cvae.decode(feats, z)
        h = torch.zeros(3, cvae.hidden)
        for t in range(200):
            rot, con, h = step(feats[t], z[t], h)
            assert torch.allclose(rot, rot_seq[t], atol=1e-4)
            assert torch.allclose(con, con_seq[t], atol=1e-5)


def test_upper_body_head_folded_for_export_is_the_head_it_was_trained_as(torch):
    """UpperBodyStep (normalisation folded in, both MLPs' outputs in one Gemm) is UpperBodyHead; on one
    frame's features broadcast over R rows of 6D (the refiner's batch) as on N rows."""
    from models.nets import UpperBodyHead, UpperBodyStep
    head = _upper_head(torch)
    if head is None:
        pytest.skip("the shipped checkpoint has no upper-body head")
    step = UpperBodyStep(head).eval()
    feats = torch.from_numpy(_sample_features(64))
    rot = torch.randn(64, 120) * 0.1 + torch.tensor([1.0, 0, 0, 0, 1, 0]).repeat(20)
    with torch.no_grad():
        want = head(feats, rot)
        biased = rot + step.rot_bias                        # the head's output bias rides on the 6D it reads
        assert torch.allclose(step(feats, biased), want, atol=2e-5)
        assert torch.allclose(step(feats[:1], biased), head(feats[:1].expand(64, -1), rot), atol=2e-5)
        assert (want - rot).abs().max() > 1e-3            # the trained head does move the torso
    untrained = UpperBodyHead(16)
    assert torch.equal(untrained(feats, rot), rot)          # an untrained head changes nothing


def test_rolling_a_controller_moves_no_torso_joint_of_the_upper_body_head(torch):
    """Only the collars' MLP reads the controllers' orientations: the spine, chest and neck (which carry the
    pelvis and the legs, hung from the headset) do not move when a controller turns; the collars do."""
    from models.nets import COLLAR_JOINTS, TORSO_JOINTS, _columns
    from edge.features import NUM_FEATURES
    head = _upper_head(torch)
    if head is None:
        pytest.skip("the shipped checkpoint has no upper-body head")
    feats = torch.from_numpy(_sample_features(64))
    rot = torch.tensor([1.0, 0, 0, 0, 1, 0]).repeat(64, 20)
    turned = feats.clone()
    turned[:, NUM_FEATURES + 6:] = turned[:, NUM_FEATURES + 6:].flip(0)      # other frames' controller turns
    with torch.no_grad():
        a, b = head(feats, rot), head(turned, rot)
    torso, collars = _columns(TORSO_JOINTS), _columns(COLLAR_JOINTS)
    assert torch.equal(a[:, torso], b[:, torso])
    assert (a[:, collars] - b[:, collars]).abs().max() > 1e-3
    rest = [c for c in range(120) if c not in torso + collars]
    assert torch.equal(a[:, rest], rot[:, rest])


def test_onnx_autoencoder_matches_pytorch(torch):
    _, ae = _torch_models(torch)
    _, _, onnx_ae = load_models(precision="fp32")
    x = np.random.default_rng(0).standard_normal((64, 63)).astype(np.float32) * 0.3
    with torch.no_grad():
        ref = ae(torch.from_numpy(x)).numpy()
    assert np.abs(onnx_ae(x) - ref).max() < 1e-4


def test_learned_prior_step_at_zero_epsilon_decodes_the_prior_mean(torch):
    """--learned-prior: the exported step maps epsilon through p(z | x, h); epsilon = 0 (N=1) must be
    the frame-by-frame prior-mean decoding training validates with."""
    from models.nets import LATENT, CVAE, DecoderStep
    torch.manual_seed(0)
    cvae = CVAE(posterior=True, learned_prior=True).eval()
    x = torch.randn(40, 3, cvae.n_features)
    step = DecoderStep(cvae).eval()
    with torch.no_grad():
        rot_seq, con_seq, _ = cvae.decode_prior_mean(x)
        h = torch.zeros(3, 128)
        for t in range(40):
            rot, con, h = step(x[t], torch.zeros(3, LATENT), h)
            assert torch.allclose(rot, rot_seq[t], atol=1e-5) and torch.allclose(con, con_seq[t], atol=1e-6)
        # and a non-zero epsilon moves the pose: the prior has a spread
        rot_eps, _, _ = step(x[0], torch.ones(3, LATENT), torch.zeros(3, 128))
        assert not torch.allclose(rot_eps, step(x[0], torch.zeros(3, LATENT), torch.zeros(3, 128))[0])


def test_vigorous_windows_are_those_that_lift_a_toe():
    """--vigorous draws from the windows whose truth lifts a toe 35 cm (motion.dataset.vigorous_starts):
    a standing body lifted 50 cm over frames 100..129 makes exactly the 60-frame windows holding one
    of those frames vigorous."""
    from motion import dataset as ds
    from edge.skeleton import NUM_JOINTS, PELVIS_HEIGHT
    F = 400
    rot = np.zeros((F, NUM_JOINTS, 4), np.float32)
    rot[..., 0] = 1.0
    root = np.zeros((F, 3), np.float32)
    root[:, 1] = PELVIS_HEIGHT
    root[100:130, 1] += 0.5
    cs = ds.ClipSet(["standing"], np.array([0]), rot, root, np.zeros((F, 2), np.float32))
    starts = ds.window_starts(cs, 60)
    assert list(ds.vigorous_starts(cs, starts, 60)) == list(range(41, 130))


def test_training_windows_lose_trackers_as_often_and_as_long_as_dragposers_protocol():
    """In the protocol's windows every worn IMU drops with 1 % a frame and stays away 100 frames: about
    0.99^100 = 37 % of it is heard, and a tracker that drops inside a 60-frame window does not come
    back in it; the other windows keep one short silence (5-45 frames) at most."""
    from motion.dataset import random_imus
    rng = np.random.default_rng(0)
    worn, alive = random_imus(rng, 60, 4000, flaky=1.0)
    heard = alive[:, worn > 0]                                       # [W, worn trackers]
    assert heard.mean() == pytest.approx(0.99 ** 100, abs=0.03)
    returns = (~heard[:-1] & heard[1:])                              # silent, then heard
    drops = (heard[:-1] & ~heard[1:])
    first_drop = np.where(drops.any(0), drops.argmax(0), 60)
    assert not (returns & (np.arange(59)[:, None] > first_drop[None])).any()
    worn, alive = random_imus(rng, 60, 4000, flaky=0.0)
    silent = (~alive[:, worn > 0]).sum(0)
    assert silent.max() <= 45 and 0.05 < (silent > 0).mean() < 0.35
