"""The paper's stages' parameters (SIFT, the two correspondence tests, retrieval, the Kalman filter)
and its Table 1 as presets. Every field is declared once (``visloc.params.declare``)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from visloc.params.declare import MAX_C_INT, Control, Params, param, refuse

# One degree of great-circle arc on the mean Earth sphere (IUGG R = 6 371 008.8 m), metres.
METRES_PER_DEGREE = 2 * math.pi * 6_371_008.8 / 360.0

# Ranges that keep the filter's numbers finite (every product of dt, Q, R and P0 it forms, over any
# drive, stays far below the float maximum, and a positive variance is never so small that y' S^-1 y
# overflows or dt^4 Q underflows to 0):
MIN_DT_S, MAX_DT_S = 1e-3, 3600.0  # time between queries, s: 1 ms .. 1 hour
MAX_GEOTAG_SIGMA_M = 1e6  # so its square stays a variance <= MAX_VARIANCE
MAX_SECONDS = 1e9  # any time window, s (about 32 years)

SIFT_STAGE = ("ingest", *("paper", "refined", "refined-fast"))


@dataclass(frozen=True)
class SiftParams(Params):
    """OpenCV SIFT settings. A store records them; queries must use the same ones. A scaled store
    (``image_scale`` < 1) is a different store: its settings record the scale."""

    n_features: int = param(0, "keypoints kept per image, the strongest; 0 keeps every one (the paper: about "
                               "3200 per KITTI frame)", kind="integer", low=0, high=MAX_C_INT,
                            methods=SIFT_STAGE, flag="--sift-features")
    n_octave_layers: int = param(3, "layers per octave of SIFT's scale space", kind="integer", low=1, high=32,
                                 methods=SIFT_STAGE, flag="--sift-octave-layers")
    contrast_threshold: float = param(0.04, "SIFT's contrast threshold (the paper's 0.04; visloc ingest describes a "
                                            "new store at 0.02, and the paper's method selects its own features there)",
                                      low=0, methods=SIFT_STAGE,
                                      flag="--sift-contrast")
    edge_threshold: float = param(10.0, "SIFT's edge threshold", low=0, open_low=True, methods=SIFT_STAGE,
                                  flag="--sift-edge")
    # larger than 10: OpenCV's blur kernel overflows
    sigma: float = param(1.6, "Gaussian blur of the first octave's image", unit="px", low=0, high=10, open_low=True,
                         methods=SIFT_STAGE, flag="--sift-sigma")
    image_scale: float = param(1.0, "SIFT runs on the image resized by this factor (area interpolation); "
                                    "keypoints are mapped back to full-resolution pixels, so geometry is "
                                    "unchanged; 1 (the paper) runs on the image as it is", low=0.1, high=1,
                               methods=SIFT_STAGE, flag="--sift-scale")

    def as_dict(self) -> dict:
        # image_scale is recorded only when it is not 1, so stores built before it existed still match
        d = asdict(self)
        if d["image_scale"] == 1.0:
            del d["image_scale"]
        return d


PAPER_ONLY = ("paper", "refined")  # the exact paths; the camera-rate path matches to 3D points instead


@dataclass(frozen=True)
class MatchParams(Params):
    """Correspondence tests of the paper's section 3.1, equations (1) and (2)."""

    tau1: float = param(
        0.8, "Lowe ratio threshold, equation (1): d1^2 / d2^2 < tau1^2", low=0, high=1, open_low=True,
        methods=PAPER_ONLY,
        control=Control("τ1 (Lowe ratio)", 0.5, 1.0, 0.01, "matching",
                        # short hints: a tooltip opens above its control and must not hide the one above
                        hint="Ratio test: lower = stricter"))
    tau2: float = param(
        0.97, "cosine similarity threshold, equation (2): cos(g, f) > tau2", low=-1, high=1, methods=PAPER_ONLY,
        control=Control("τ2 (cosine)", 0.8, 1.0, 0.005, "matching",
                        hint="Cosine test: higher = stricter"))


@dataclass(frozen=True)
class RetrievalParams(Params):
    """Which database images a query is compared with. The first query, and any query after one
    without a match, scans everything."""

    window_s: float = param(
        20.0, "later queries search database images within +-this of the previous best match's time (the "
              "paper: 20 s)", unit="s", low=0, high=MAX_SECONDS, open_low=True, methods=PAPER_ONLY,
        control=Control("Search window ± (s)", 1.0, 60.0, 1.0, "queries",
                        hint="Paper and refined modes: search database images within ± this many seconds of the "
                             "previous best match. refined-fast searches a shortlist instead"))
    exclusion_s: float = param(
        0.0, "database images closer in time to the query than this are not used (0: off, normal use; 1 s in "
             "the paper's evaluation, where database and queries come from the same drive)",
        unit="s", low=0, high=MAX_SECONDS,
        control=Control("Exclusion (s)", 0.0, 3.0, 0.1, "queries", initial=1.0,
                        hint="Database images closer in time to the query than this (s) are not allowed as "
                             "matches, so the query cannot match a picture taken from the same place at the same "
                             "moment"))


@dataclass(frozen=True)
class FilterParams(Params):
    """Constant-velocity Kalman filter, equations (3)-(7), in a local metric frame.

    Q = accel_var_m2_s4 * G G^T with G = [dt^2/2, dt] per axis (piecewise-constant white
    acceleration). See ``PAPER_FILTER`` for how Table 1's values map onto these. Each range keeps
    every number the filter forms finite. R = 0 (exact measurements) needs P0 > 0, else the
    innovation covariance S = H P H' + R of the first measurement is 0 and singular, and Q > 0,
    else two exact measurements fix position and velocity, the predicted P becomes 0 and S is
    singular from the third measurement on.
    """

    dt_s: float = param(1.0, "time between queries (Table 1: 1 s); the query sequence is sampled at this "
                             "interval too", unit="s", low=MIN_DT_S, high=MAX_DT_S)
    meas_var_m2: float = param(
        (1e-4 * METRES_PER_DEGREE) ** 2, "measurement variance of a geotag measurement, R = this * I (the paper's "
                                         "0.0001 deg read as a standard deviation: 11.12 m)",
        unit="m^2", kind="variance", symbol="R",
        control=Control("R: meas. σ (m)", 0.1, 40.0, 0.01, "filter", shows="sigma",
                        hint="R = σ² I: how far (m) the filter expects a geotag measurement to be off. The paper's "
                             "0.0001° is 11.12 m. Refined poses bring their own R"))
    accel_var_m2_s4: float = param(
        1.0, "white acceleration variance of the constant-velocity model, Q, over the paper's 1 s query interval "
             "(queried faster, the filter scales it by 1 s / interval: the velocity may change as much in a second "
             "at any rate)", unit="m^2/s^4", kind="variance",
        symbol="Q",
        control=Control("Q: accel. σ (m/s²)", 0.0, 5.0, 0.05, "filter", shows="sigma",
                        hint="Process noise Q: how hard (m/s²) the filter expects the car to accelerate over a "
                             "second (constant-velocity model, white acceleration; the same car at any query rate)"))
    init_var: float = param(
        1000.0, "initial uncertainty, P0 = this * I (m^2 on position, m^2/s^2 on velocity; Table 1's 'Q = I x "
                "1000')", unit="m^2, m^2/s^2", kind="variance", symbol="P0",
        control=Control("P0: initial σ (m, m/s)", 1.0, 100.0, 0.1, "filter", shows="sigma",
                        hint="P0 = σ² I: the filter's initial uncertainty, σ in m for the position and m/s for the "
                             "velocity. The paper's 1000·I is σ = 31.6"))
    maneuver_accel_var_m2_s4: float = param(
        16.0, "with a gate (the refined methods), a measurement the gate would reject is tested once more "
              "against the prediction made with this process noise instead of Q, and applied with it if it fits "
              "(the car turned or braked harder than Q allows); 0 never does (16: 4 m/s^2, a firm brake)",
        unit="m^2/s^4", kind="variance", methods=("refined", "refined-fast"))

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.meas_var_m2 == 0 and self.init_var == 0:
            raise refuse("meas_var_m2 (R)=0 with init_var (P0)=0: the innovation covariance S = P + R of the first "
                         "measurement would be 0, a singular matrix; give R or P0 a value > 0",
                         "meas_var_m2", "init_var")
        if self.meas_var_m2 == 0 and self.accel_var_m2_s4 == 0:
            raise refuse("meas_var_m2 (R)=0 with accel_var_m2_s4 (Q)=0: after two exact measurements the predicted "
                         "covariance P is 0, so the innovation covariance S = P + R would be singular; give R or Q "
                         "a value > 0", "meas_var_m2", "accel_var_m2_s4")


# The paper's Table 1, mapped onto our parameters:
#  tau1 = 0.8, tau2 = 0.97: as printed.
#  R = 0.0001 decimal degree: read as the standard deviation of the measured
#      position, 0.0001 deg of arc = 11.12 m, so R = 11.12^2 = 123.6 m^2 on each
#      axis. (Read as a variance in deg^2 it would be a 1.1 km standard deviation,
#      which would make the filter ignore measurements that are ~10 m off.)
#  "Q = I x 1000, initial state prediction noise": the initial uncertainty P0 =
#      1000 * I (m^2, m^2/s^2): 31.6 m and 31.6 m/s, "much higher than the
#      measurement noise", as section 4 says.
#  The paper gives no process noise; we use white acceleration of 1 m/s^2
#      standard deviation, an ordinary car's.
#  dt = 1 s.
PAPER_SIFT = SiftParams()
# A new store keeps every keypoint SIFT finds at half the paper's contrast threshold (COLMAP's, the
# COLMAP-style peer's): the refined measurement's support. The paper's own features are the stored ones
# whose response reaches 0.04 (``visloc.features.sift.contrast_kept``), selected for the paper's method
# and for retrieval, so one store serves both (docs/performance.md, "Denser SIFT").
STORE_SIFT = PAPER_SIFT.replace(contrast_threshold=0.02)
PAPER_MATCH = MatchParams(tau1=0.8, tau2=0.97)
PAPER_RETRIEVAL = RetrievalParams(window_s=20.0, exclusion_s=0.0)
PAPER_EVAL_RETRIEVAL = RetrievalParams(window_s=20.0, exclusion_s=1.0)
PAPER_FILTER = FilterParams(dt_s=1.0, meas_var_m2=(1e-4 * METRES_PER_DEGREE) ** 2, accel_var_m2_s4=1.0, init_var=1000.0)
