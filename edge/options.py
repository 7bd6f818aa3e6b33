"""What a Pipeline is built from, as one value: `edge eval`, `edge replay`, the board config
(firmware_bridge.config.Config.pipeline_options) and the service all make a PipelineOptions and hand it
to Pipeline(options, models, criteria).

    Pipeline(PipelineOptions(samples=16, precision="int8", refine={"steps": 2}))
    replace(options, samples=1)          # dataclasses.replace: a variant of the same options
"""
from dataclasses import dataclass

from edge.heading import HeadingSettings
from edge.inference import DEFAULT_PRECISION
from edge.ik import ELBOW_FROM_HAND
from edge.physics import LEG_GUARD_M
from edge.refine import RefineSettings
from edge.smooth import BETA, MIN_CUTOFF_HZ

MAX_SAMPLES = 128


@dataclass(frozen=True)
class PipelineOptions:
    samples: int = 1                    # latent samples N (1: the plain CVAE at the prior mean)
    seed: int = 0                       # the samples' latents are drawn once from this seed
    fps: float = 60.0                   # the frame rate of the tracker signals
    body_scale: float = 1.0             # the wearer's size against the canonical body (T-pose calibration)
    precision: str = DEFAULT_PRECISION  # "int8" or "fp32" (int8 falls back when its self-check fails)
    threads: int = 1                    # ONNX Runtime intra-op threads
    lookahead: int = 0                  # SSI look-ahead tau: the output is frame t - tau (offline use)
    transition: int = 10                # frames a move between samples is eased over
    ssi: bool = True                    # switch samples (N > 1); False keeps sample 0
    foot_ik: bool = True                # foot-contact locks and leg IK
    leg_guard: float = LEG_GUARD_M      # the foot IK keeps a free leg this far from the other (m; 0: off)
    arm_ik: bool = True                 # arm IK to the controllers
    elbow_from_hand: float = ELBOW_FROM_HAND    # how far the controller's hand axis turns the elbow (0: off)
    smooth_min_cutoff: float = MIN_CUTOFF_HZ    # the upper body's one-euro filter (edge.smooth; Hz, 0: off)
    smooth_beta: float = BETA                   # its cut-off's rise with speed
    use_native: bool = True             # the compiled core when a C compiler is there
    segments: bool = True               # a worn IMU sets its segment's world rotation
    selection: dict = None              # SSI's selection settings; None: the model manifest's
    refine: RefineSettings = None       # latent refinement (edge.refine); None: off
    heading: HeadingSettings = HeadingSettings()    # the extra IMUs' heading observer; None: off

    def __post_init__(self):
        # A config's or caller's forms, made the one form: refine / heading as True, a dict or settings.
        object.__setattr__(self, "lookahead", 0 if self.lookahead is None else int(self.lookahead))
        object.__setattr__(self, "refine", RefineSettings.parse(self.refine))
        object.__setattr__(self, "heading", HeadingSettings.parse(self.heading))
        if not 1 <= self.samples <= MAX_SAMPLES:
            raise ValueError(f"samples must be 1..{MAX_SAMPLES}, got {self.samples}")
        if self.lookahead < 0 or self.transition < 1:
            raise ValueError("lookahead must be >= 0 and transition >= 1 frames")
        if self.precision not in ("fp32", "int8"):
            raise ValueError(f"precision must be 'fp32' or 'int8', got {self.precision!r}")
