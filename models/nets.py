"""The SSI networks (section 4.2) in PyTorch: the CVAE and the pose autoencoder, plus one-step export wrappers."""
import torch
from torch import nn

from edge.features import NUM_DECODER_FEATURES, NUM_FEATURES, NUM_ORIENTATION_FEATURES
from edge.skeleton import JOINT, LEVELS, NUM_JOINTS, NUM_PREDICTED, OFFSETS, PARENTS

LATENT = 30
HIDDEN = 128          # v0.3's GRU width; CVAE(hidden=...) picks another (the checkpoint and manifest carry it)
ROT_OUT = NUM_PREDICTED * 6
# 6D of the identity, so an untrained head starts at the rest pose.
_IDENTITY_6D = torch.tensor([1.0, 0, 0, 0, 1.0, 0]).repeat(NUM_PREDICTED)


def matrix_from_6d(r6):
    a, b = r6[..., 0:3], r6[..., 3:6]
    x = nn.functional.normalize(a, dim=-1)
    y = nn.functional.normalize(b - (x * b).sum(-1, keepdim=True) * x, dim=-1)
    return torch.stack([x, y, torch.cross(x, y, dim=-1)], dim=-1)


def fk_positions(root_rot, local_rot):
    """root_rot [...,3,3], local_rot [...,J-1,3,3] -> joint positions [...,J,3] with the pelvis at the origin."""
    offsets = torch.as_tensor(OFFSETS, dtype=local_rot.dtype, device=local_rot.device)
    rots = [None] * NUM_JOINTS
    pos = [None] * NUM_JOINTS
    rots[0] = root_rot
    pos[0] = torch.zeros(root_rot.shape[:-2] + (3,), dtype=root_rot.dtype, device=root_rot.device)
    for idx in LEVELS:
        for j in idx:
            p = PARENTS[j]
            rots[j] = rots[p] @ local_rot[..., j - 1, :, :]
            pos[j] = pos[p] + (rots[p] @ offsets[j])
    return torch.stack(pos, dim=-2)


class Normalizer(nn.Module):
    def __init__(self, dim):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))

    def fit(self, x):
        x = x.reshape(-1, x.shape[-1])
        self.mean.copy_(x.mean(0))
        self.std.copy_(x.std(0).clamp_min(1e-3))

    def forward(self, x):
        return (x - self.mean) / self.std


class CVAE(nn.Module):
    """Encoder: FC F->H, GRU H, mu/logvar 30. Decoder: FC 30+F->H, GRU H, ReLU, rotation and contact heads
    (H = `hidden`, 128 in v0.3).

    posterior=True lets the encoder also see the target pose (63 head-relative joint coordinates):
    the recognition network q(z | x, y) of a conditional VAE (Sohn et al. 2015). The paper's encoder
    sees the trackers only, so z cannot carry pose information and the decoder learns to ignore it;
    the decoder, which is all that ships, is the same either way.

    learned_prior=True adds a conditional prior p(z | x_t, h_{t-1}) = N(mu_p, sigma_p) computed from
    the trackers and the decoder's GRU state; the KL term is KL(q || p), and the shipped decoder step
    maps the runtime's epsilon to z = mu_p + sigma_p * epsilon inside the graph. epsilon = 0 (N=1) is
    then the prior's mean, not z = 0, and the spread of the samples follows how ambiguous the pose is
    given the trackers (wide for legs during a kick, narrow when standing).
    """

    def __init__(self, posterior=False, learned_prior=False, n_features=NUM_FEATURES, hidden=HIDDEN):
        super().__init__()
        self.posterior, self.learned_prior, self.n_features = posterior, learned_prior, n_features
        self.hidden = H = hidden
        F = n_features          # 24 for the models before the extra IMUs, 24 + 49 since (edge.features)
        self.prior = nn.Sequential(nn.Linear(F + H, H), nn.ReLU(),
                                   nn.Linear(H, 2 * LATENT)) if learned_prior else None
        self.norm = Normalizer(F)
        self.target_norm = Normalizer(NUM_JOINTS * 3) if posterior else None
        self.enc_fc = nn.Linear(F + (NUM_JOINTS * 3 if posterior else 0), H)
        self.enc_gru = nn.GRU(H, H)
        self.mu = nn.Linear(H, LATENT)
        self.logvar = nn.Linear(H, LATENT)
        self.dec_fc = nn.Linear(LATENT + F, H)
        self.dec_gru = nn.GRU(H, H)
        self.rot_head = nn.Linear(H, ROT_OUT)
        self.contact_head = nn.Linear(H, 2)

    def encode(self, x, target=None):
        inp = self.norm(x)
        if self.posterior:
            inp = torch.cat([inp, self.target_norm(target.flatten(-2))], dim=-1)
        h, _ = self.enc_gru(torch.relu(self.enc_fc(inp)))
        return self.mu(h), self.logvar(h).clamp(-10, 5)

    def decode(self, x, z, h0=None):
        rot, con, h = self._decode_seq(x, z, h0)
        return rot, con, h[-1:]

    def _decode_seq(self, x, z, h0=None):
        inp = torch.relu(self.dec_fc(torch.cat([z, self.norm(x)], dim=-1)))
        h, _ = self.dec_gru(inp, h0)
        y = torch.relu(h)
        return self.rot_head(y) + _IDENTITY_6D.to(y.device), torch.sigmoid(self.contact_head(y)), h

    def prior_params(self, x_norm, h_prev):
        """Conditional prior from normalised features and the previous GRU state -> (mu_p, logvar_p)."""
        out = self.prior(torch.cat([x_norm, h_prev], dim=-1))
        return out[..., :LATENT], out[..., LATENT:].clamp(-8, 3)

    def forward(self, x, sample=True, target=None):
        """x [W,B,24] time-major -> rot6d [W,B,120], contacts [W,B,2], mu, logvar (posterior), and
        the prior's (mu_p, logvar_p) per frame when it is learned (else None)."""
        mu, logvar = self.encode(x, target)
        z = mu + torch.exp(0.5 * logvar) * torch.randn_like(mu) if sample else mu
        rot, con, h = self._decode_seq(x, z)
        prior = None
        if self.learned_prior:
            h_prev = torch.cat([torch.zeros_like(h[:1]), h[:-1]], dim=0)
            prior = self.prior_params(self.norm(x), h_prev)
        return rot, con, mu, logvar, prior

    def decode_prior_mean(self, x):
        """Frame-by-frame decoding at epsilon = 0, as N=1 runs: z_t = 0, or mu_p(x_t, h_{t-1})."""
        if not self.learned_prior:
            return self.decode(x, torch.zeros(x.shape[:-1] + (LATENT,), device=x.device))
        h = torch.zeros((1,) + x.shape[1:-1] + (self.hidden,))
        xn, rots, cons = self.norm(x), [], []
        for t in range(len(x)):
            z, _ = self.prior_params(xn[t:t + 1], h)
            rot, con, h = self.decode(x[t:t + 1], z, h)
            rots.append(rot)
            cons.append(con)
        return torch.cat(rots), torch.cat(cons), h

# The upper-body head (v0.5): which of the CVAE's 6D outputs it moves, and which it reads.
TORSO_JOINTS = ("spine", "chest", "neck")       # they carry the pelvis and the legs, hung from the headset
COLLAR_JOINTS = ("l_collar", "r_collar")         # they carry the shoulders and the arms only
READS_6D = 9 * 6                                 # the 6D of spine .. r_collar (predicted joints 0-8)
HEAD_ORIENTATION = NUM_FEATURES + 6              # features[:79]: the CVAE's 73 and the headset's orientation


def _columns(names):
    return [(JOINT[n] - 1) * 6 + k for n in names for k in range(6)]


class _Branch(nn.Module):
    """relu(W_f f + W_r r) -> relu(W h) -> out: the features part and the 6D part in two layers, so that a
    frame's features (one row) broadcast over the refiner's R latents (JacobianStep)."""

    def __init__(self, n_features, hidden, n_out):
        super().__init__()
        self.in_f = nn.Linear(n_features, hidden)
        self.in_r = nn.Linear(READS_6D, hidden, bias=False)
        self.mid = nn.Linear(hidden, hidden)
        self.out = nn.Linear(hidden, n_out)
        nn.init.zeros_(self.out.weight)         # an untrained head changes nothing
        nn.init.zeros_(self.out.bias)

    def hidden(self, f, r):
        return torch.relu(self.mid(torch.relu(self.in_f(f) + self.in_r(r))))


class UpperBodyHead(nn.Module):
    """The CVAE decodes the torso and collars from positions alone, and the headset's orientation says much
    about the neck and chest that positions do not (issue #41: the shoulders 4.8-5.6 cm off on unseen
    people, with the head exact). This head adds to the CVAE's 6D of the spine, chest and neck what an
    MLP reads from the CVAE's features, its 6D of spine..collars and the headset's orientation; and to the
    collars' what a second MLP reads from all of that and the controllers' orientations (the reach a
    hand's roll and bend tell, LoBSTR/SSI do not model it). The torso's MLP never reads a controller's
    orientation, so rolling a controller about the wrist moves the collars and arms and never the legs.

    features [...,91] (edge.features: the CVAE's 73, then headset and controller orientations),
    rot6d [...,120] -> rot6d [...,120]."""

    def __init__(self, hidden=64):
        super().__init__()
        self.hidden_size = hidden
        self.norm_f = Normalizer(NUM_DECODER_FEATURES)
        self.norm_r = Normalizer(READS_6D)
        self.torso = _Branch(HEAD_ORIENTATION, hidden, 6 * len(TORSO_JOINTS))
        self.collars = _Branch(NUM_DECODER_FEATURES, hidden, 6 * len(COLLAR_JOINTS))
        place = torch.zeros(6 * (len(TORSO_JOINTS) + len(COLLAR_JOINTS)), ROT_OUT)
        place[torch.arange(len(place)), _columns(TORSO_JOINTS + COLLAR_JOINTS)] = 1.0
        self.register_buffer("place", place)     # [30,120]: the two MLPs' outputs into the 6D vector

    def delta(self, features, rot6d):
        f, r = self.norm_f(features), self.norm_r(rot6d[..., :READS_6D])
        t = self.torso.out(self.torso.hidden(f[..., :HEAD_ORIENTATION], r))
        c = self.collars.out(self.collars.hidden(f, r))
        return torch.cat([t, c], dim=-1) @ self.place

    def forward(self, features, rot6d):
        return rot6d + self.delta(features, rot6d)


class UpperBodyStep(nn.Module):
    """UpperBodyHead in inference form, in as few graph nodes as the same function allows: at N=16 ONNX
    Runtime's per-node cost (about 0.6 us on an Intel Xeon) is as large as the head's arithmetic.
    - The normalisation is folded into the first layer; the two MLPs run side by side, one Gemm per
      layer (the torso's half with zero weights on the controllers' columns, the middle layer and the
      output block-diagonal).
    - The features' part of the first layer is its own Gemm on one row (a frame's rows share it), the
      Gemm of the 6D part adds it (Gemm's C, broadcast) and ORT fuses the ReLU.
    - The output layer writes straight into the 6D vector: its weights placed on the 120 columns and
      the 6D it adds to as Gemm's C. Its bias rides on the CVAE's rotation head (`rot_bias`: DecoderStep
      adds it there), taken back out of the 6D the first layer reads.
    The runtime runs it in fp32 (quantize.build.head_layers), where a zero weight contributes exactly
    nothing: a controller's orientation still never reaches the torso."""

    def __init__(self, head: UpperBodyHead):
        super().__init__()
        mf, sf = head.norm_f.mean.double(), head.norm_f.std.double()
        mr, sr = head.norm_r.mean.double(), head.norm_r.std.double()
        H, F = head.hidden_size, NUM_DECODER_FEATURES
        w_f = torch.zeros(2 * H, F, dtype=torch.float64)
        w_r = torch.zeros(2 * H, READS_6D, dtype=torch.float64)
        bias = torch.zeros(2 * H, dtype=torch.float64)
        for k, (branch, n) in enumerate(((head.torso, HEAD_ORIENTATION), (head.collars, F))):
            wf = branch.in_f.weight.double() / sf[:n]
            wr = branch.in_r.weight.double() / sr
            w_f[k * H:(k + 1) * H, :n], w_r[k * H:(k + 1) * H] = wf, wr
            bias[k * H:(k + 1) * H] = branch.in_f.bias.double() - wf @ mf[:n] - wr @ mr
        place = head.place.double()                                     # [30,120]
        t, c = head.torso.out, head.collars.out
        out_w = torch.block_diag(t.weight.detach(), c.weight.detach()).double()           # [30,2H]
        rot_bias = torch.cat([t.bias, c.bias]).double() @ place                           # [120]
        self.register_buffer("rot_bias", rot_bias.float())
        self.first_f = _linear(w_f, bias - w_r @ rot_bias[:READS_6D])  # the 6D read carries rot_bias
        self.first_r = _AddTo(w_r)
        mid = torch.block_diag(head.torso.mid.weight.detach(), head.collars.mid.weight.detach())
        self.mid = _linear(mid, torch.cat([head.torso.mid.bias, head.collars.mid.bias]))
        self.out = _AddTo(place.t() @ out_w)                           # [120,2H]: straight into the 6D

    def forward(self, features, rot6d):
        """features [1 or N,F], rot6d [N,120] carrying rot_bias (the trained head's input + rot_bias:
        DecoderStep's rotation head adds it) -> rot6d [N,120], what UpperBodyHead gives on rot6d - rot_bias."""
        h = torch.relu(self.first_r(self.first_f(features), rot6d[:, :READS_6D]))
        return self.out(rot6d, torch.relu(self.mid(h)))


class DecoderStep(nn.Module):
    """One decoder frame in inference form, for export: the same function as CVAE.decode's step in
    fewer, larger graph nodes, since at N=100 ONNX Runtime's per-node cost rivals the arithmetic.

    - The feature normalisation is folded into the first layer's weights and bias.
    - The GRU cell is written out as Gemm + Sigmoid/Tanh (ONNX Runtime cannot quantize the GRU op),
      with its reset and update gates in one Gemm over [x, h] (their input and hidden parts are
      summed anyway) and the candidate's input and hidden parts in two.
    - h' = (1 - u) n + u h is computed as n + u (h - n); the rest pose's 6D is folded into the
      rotation head's bias.

    - With an upper-body head (v0.5 on, UpperBodyHead) the graph reads the headset's and controllers'
      orientations after the CVAE's features, and its rot6d is the head's.

    Inputs: features [N,F] or [1,F] (F = 24 + 49, + 18 with the head; one row is every row's), latent [N,30],
    hidden [N,H]; outputs: rot6d [N,120], contacts [N,2], hidden [N,H].
    """

    def __init__(self, cvae: CVAE, upper: UpperBodyHead = None):
        super().__init__()
        self.n_cvae = cvae.n_features
        self.upper = None if upper is None else UpperBodyStep(upper)
        self.hidden = H = cvae.hidden
        assert upper is None or cvae.n_features == NUM_FEATURES, "the upper-body head follows the CVAE's 73 features"
        g = cvae.dec_gru
        self.prior = cvae.prior
        self.norm = cvae.norm           # the learned prior still reads normalised features
        mean, std = cvae.norm.mean.double(), cvae.norm.std.double()     # folded in float64, stored as float32
        w = cvae.dec_fc.weight[:, LATENT:].double() / std                 # fc over [latent, (x - mean) / std]
        bias = cvae.dec_fc.bias.double() - w @ mean
        if upper is not None:           # the head's orientation columns: zero weights (fp32 at run time, so exact)
            w = torch.cat([w, torch.zeros(H, NUM_ORIENTATION_FEATURES, dtype=w.dtype)], 1)
        # The first layer in its latent and feature parts: a frame's rows share their features, so the
        # runtime feeds one row of them and the graph broadcasts it (the larger part, once per frame).
        self.fc_features = _linear(w, bias)
        self.fc_latent = _AddTo(cvae.dec_fc.weight[:, :LATENT])
        self.gates_ru = _linear(torch.cat([g.weight_ih_l0[:2 * H], g.weight_hh_l0[:2 * H]], 1),
                                g.bias_ih_l0[:2 * H] + g.bias_hh_l0[:2 * H])
        self.cand_x = _linear(g.weight_ih_l0[2 * H:], g.bias_ih_l0[2 * H:])
        self.cand_h = _linear(g.weight_hh_l0[2 * H:], g.bias_hh_l0[2 * H:])
        rot_bias = cvae.rot_head.bias + _IDENTITY_6D
        if self.upper is not None:      # the head's output bias, added here for nothing (UpperBodyStep)
            rot_bias = rot_bias + self.upper.rot_bias
        self.rot_head = _linear(cvae.rot_head.weight, rot_bias)
        self.contact_head = cvae.contact_head

    def forward(self, features, latent, hidden):
        if self.prior is not None:      # epsilon -> z through the learned conditional prior (on the CVAE's 73)
            f = features[:, :self.n_cvae].expand(hidden.shape[0], -1)
            out = self.prior(torch.cat([self.norm(f), hidden], dim=-1))
            latent = out[:, :LATENT] + torch.exp(0.5 * out[:, LATENT:].clamp(-8, 3)) * latent
        x = torch.relu(self.fc_latent(self.fc_features(features), latent))   # [1 or N,H] + [N,H]
        ru = torch.sigmoid(self.gates_ru(torch.cat([x, hidden], dim=-1)))
        r, u = ru[:, :self.hidden], ru[:, self.hidden:]
        n = torch.tanh(self.cand_x(x) + r * self.cand_h(hidden))
        h = n + u * (hidden - n)
        y = torch.relu(h)
        rot = self.rot_head(y)
        if self.upper is not None:
            rot = self.upper(features, rot)
        return rot, torch.sigmoid(self.contact_head(y)), h


class JacobianStep(nn.Module):
    """DecoderStep's rot6d for R latents that share one frame's features and GRU state: the batch the
    refiner (edge.refine) differentiates by forward differences. What the rows share is computed once
    (the first layer's feature part, the gates' and the candidate's hidden parts: about half of a
    row's arithmetic), and only the rotations are made (the refiner needs nothing else).

    Inputs: features [1,F], latent [R,30], hidden [1,128]; output: rot6d [R,120], row r equal to
    DecoderStep's rot6d for (features, latent[r], hidden) up to float rounding."""

    def __init__(self, cvae: CVAE, upper: UpperBodyHead = None):
        super().__init__()
        d = DecoderStep(cvae, upper)
        self.n_cvae, self.upper = d.n_cvae, d.upper
        self.hidden = H = d.hidden
        self.prior, self.norm = d.prior, d.norm
        self.fc_features, self.fc_latent = d.fc_features, d.fc_latent
        w, b = d.gates_ru.weight.detach(), d.gates_ru.bias.detach()
        self.gates_x = _linear(w[:, :H], torch.zeros(2 * H))
        self.gates_h = _linear(w[:, H:], b)
        self.cand_x, self.cand_h, self.rot_head = d.cand_x, d.cand_h, d.rot_head

    def forward(self, features, latent, hidden):
        if self.prior is not None:      # as DecoderStep: epsilon -> z through the learned conditional prior
            out = self.prior(torch.cat([self.norm(features[:, :self.n_cvae]), hidden], dim=-1))
            latent = out[:, :LATENT] + torch.exp(0.5 * out[:, LATENT:].clamp(-8, 3)) * latent
        x = torch.relu(self.fc_latent(self.fc_features(features), latent))   # [1,H] + [R,H]
        ru = torch.sigmoid(self.gates_x(x) + self.gates_h(hidden))
        r, u = ru[:, :self.hidden], ru[:, self.hidden:]
        n = torch.tanh(self.cand_x(x) + r * self.cand_h(hidden))
        h = n + u * (hidden - n)
        rot = self.rot_head(torch.relu(h))
        return rot if self.upper is None else self.upper(features, rot)     # features [1,F] broadcast over R


class _AddTo(nn.Module):
    """c + x @ weight.T: a Linear whose bias is a tensor given at call time (Gemm's C, broadcast), here a
    part computed once per frame or the 6D vector the head adds to."""

    def __init__(self, weight):
        super().__init__()
        self.register_buffer("weight_t", weight.detach().t().float().contiguous())

    def forward(self, c, x):
        return torch.addmm(c, x, self.weight_t)


def _linear(weight, bias):
    """An nn.Linear holding copies of these weights."""
    layer = nn.Linear(weight.shape[1], weight.shape[0])
    with torch.no_grad():
        layer.weight.copy_(weight)
        layer.bias.copy_(bias)
    return layer


class PoseAE(nn.Module):
    """SSI anomaly autoencoder: local joint positions (J*3) -> 28 -> 14 -> 7 -> 7 -> 14 -> 28 -> rotations (6 per predicted joint)."""

    SIZES = (NUM_JOINTS * 3, 28, 14, 7, 7, 14, 28, ROT_OUT)

    def __init__(self):
        super().__init__()
        self.norm = Normalizer(NUM_JOINTS * 3)
        layers = []
        for a, b in zip(self.SIZES[:-1], self.SIZES[1:], strict=True):
            layers += [nn.Linear(a, b), nn.ReLU()]
        self.net = nn.Sequential(*layers[:-1])
        self.register_buffer("identity6d", _IDENTITY_6D.clone())

    def forward(self, positions):
        return self.net(self.norm(positions)) + self.identity6d


class AEStep(nn.Module):
    """The pose autoencoder in inference form, for export: normalisation folded into the first layer
    and the rest pose's 6D into the last bias (three graph nodes fewer; the same function)."""

    def __init__(self, ae: PoseAE):
        super().__init__()
        layers = list(ae.net)
        first, last = layers[0], layers[-1]
        w = first.weight.double() / ae.norm.std.double()
        self.net = nn.Sequential(_linear(w, first.bias.double() - w @ ae.norm.mean.double()), *layers[1:-1],
                                 _linear(last.weight, last.bias + ae.identity6d))

    def forward(self, positions):
        return self.net(positions)
