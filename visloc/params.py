"""Typed, validated parameters of every stage, with the paper's values as presets.

Every class is a frozen dataclass that checks itself in ``__post_init__`` and
raises ``ParameterError`` naming the parameter. Units are in the field names.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

from visloc.errors import ParameterError

# One degree of great-circle arc on the mean Earth sphere (IUGG R = 6 371 008.8 m), metres.
METRES_PER_DEGREE = 2 * math.pi * 6_371_008.8 / 360.0


# Ranges that keep the filter's numbers finite (every product of dt, Q, R and P0 it forms, over any
# drive, stays far below the float maximum, and a positive variance is never so small that y' S^-1 y
# overflows or dt^4 Q underflows to 0):
MIN_DT_S, MAX_DT_S = 1e-3, 3600.0  # time between queries, s: 1 ms .. 1 hour
MIN_VARIANCE, MAX_VARIANCE = 1e-12, 1e12  # a positive R, Q or P0, in its units
MAX_GEOTAG_SIGMA_M = 1e6  # so its square stays a variance <= MAX_VARIANCE
MAX_SECONDS = 1e9  # any time window, s (about 32 years)
MAX_C_INT = 2**31 - 1  # integers handed to OpenCV


def _refuse(message: str, *names: str) -> ParameterError:
    """A ``ParameterError``; ``names`` (the fields at fault) let the command line name its flags."""
    err = ParameterError(message)
    err.params = names  # type: ignore[attr-defined]
    return err


def _check(name: str, value: float, ok: bool, rule: str) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and ok):
        raise _refuse(f"{name}={value!r}: must be {rule}", name.split(" ")[0])


def _variance(name: str, value: float) -> None:
    _check(name, value, value == 0 or MIN_VARIANCE <= value <= MAX_VARIANCE,
           f">= 0 (0 or in [{MIN_VARIANCE:g}, {MAX_VARIANCE:g}])")


class _Params:
    def as_dict(self) -> dict:
        return asdict(self)  # type: ignore[call-overload]

    def replace(self, **changes):
        names = {f.name for f in fields(self)}  # type: ignore[arg-type]
        unknown = set(changes) - names
        if unknown:
            raise ParameterError(f"unknown parameter {sorted(unknown)[0]!r} for {type(self).__name__}")
        return replace(self, **changes)  # type: ignore[type-var]


@dataclass(frozen=True)
class SiftParams(_Params):
    """OpenCV SIFT settings. A store records them; queries must use the same ones.

    ``n_features = 0`` keeps every keypoint (the paper: about 3200 per KITTI frame).
    ``image_scale`` < 1 runs SIFT on the image resized by that factor (area
    interpolation) and maps keypoints back to full-resolution pixels, so geometry
    is unchanged; 1 (the paper) runs on the image as it is. A scaled store is a
    different store: its settings record the scale.
    """

    n_features: int = 0
    n_octave_layers: int = 3
    contrast_threshold: float = 0.04
    edge_threshold: float = 10.0
    sigma: float = 1.6
    image_scale: float = 1.0

    def as_dict(self) -> dict:
        # image_scale is recorded only when it is not 1, so stores built before it existed still match
        d = asdict(self)
        if d["image_scale"] == 1.0:
            del d["image_scale"]
        return d

    def __post_init__(self) -> None:
        _check("n_features", self.n_features,
               isinstance(self.n_features, int) and 0 <= self.n_features <= MAX_C_INT,
               f"an integer in [0, {MAX_C_INT}] (0 keeps every keypoint)")
        _check("n_octave_layers", self.n_octave_layers,
               isinstance(self.n_octave_layers, int) and 1 <= self.n_octave_layers <= 32, "an integer in [1, 32]")
        _check("contrast_threshold", self.contrast_threshold, self.contrast_threshold >= 0, ">= 0")
        _check("edge_threshold", self.edge_threshold, self.edge_threshold > 0, "> 0")
        _check("sigma", self.sigma, 0 < self.sigma <= 10, "in (0, 10]")  # larger: OpenCV's blur kernel overflows
        _check("image_scale", self.image_scale, 0.1 <= self.image_scale <= 1, "in [0.1, 1]")


@dataclass(frozen=True)
class MatchParams(_Params):
    """Correspondence tests of the paper's section 3.1.

    tau1: Lowe's ratio, equation (1): d1^2 / d2^2 < tau1^2, tau1 in (0, 1].
    tau2: cosine similarity, equation (2): cos(g, f) > tau2, tau2 in [-1, 1].
    """

    tau1: float = 0.8
    tau2: float = 0.97

    def __post_init__(self) -> None:
        _check("tau1", self.tau1, 0 < self.tau1 <= 1, "in (0, 1]")
        _check("tau2", self.tau2, -1 <= self.tau2 <= 1, "in [-1, 1]")


@dataclass(frozen=True)
class RetrievalParams(_Params):
    """Which database images a query is compared with.

    window_s:    later queries search database images within +-window_s of the
                 previous best match's timestamp (the paper: 20 s). The first
                 query, and any query after one without a match, scans everything.
    exclusion_s: database images closer in time to the query than this are
                 removed (0 = off, normal use; 1 s in the paper's evaluation,
                 where database and queries come from the same drive).
    """

    window_s: float = 20.0
    exclusion_s: float = 0.0

    def __post_init__(self) -> None:
        _check("window_s", self.window_s, 0 < self.window_s <= MAX_SECONDS, f"in (0, {MAX_SECONDS:g}]")
        _check("exclusion_s", self.exclusion_s, 0 <= self.exclusion_s <= MAX_SECONDS, f"in [0, {MAX_SECONDS:g}]")


@dataclass(frozen=True)
class FilterParams(_Params):
    """Constant-velocity Kalman filter, equations (3)-(7), in a local metric frame.

    dt_s:                time between queries, s (Table 1: 1 s). The query sequence
                         is sampled at this interval too.
    meas_var_m2:         R = meas_var_m2 * I2, measurement noise variance, m^2.
    accel_var_m2_s4:     Q = accel_var_m2_s4 * G G^T with G = [dt^2/2, dt] per axis
                         (piecewise-constant white acceleration), m^2/s^4.
    init_var:            P0 = init_var * I4 (m^2 on position, m^2/s^2 on velocity).
    maneuver_accel_var_m2_s4: with a Mahalanobis gate (the refined methods; the paper's filter has
                         none), a measurement the gate would reject is tested once more against the
                         prediction made with this process noise instead of Q: if the car turned or
                         braked harder than Q allows, it fits that one and is applied with it, so the
                         filter follows the car; 0 never does. m^2/s^4 (16: 4 m/s^2, a firm brake or
                         a tight turn)

    See ``PAPER_FILTER`` for how Table 1's values map onto these.

    Ranges, so that every number the filter forms stays finite: dt_s in [MIN_DT_S, MAX_DT_S]
    (1 ms .. 1 h); each variance 0 or in [MIN_VARIANCE, MAX_VARIANCE] (1e-12 .. 1e12). R = 0 (exact
    measurements) needs P0 > 0, else the innovation covariance S = H P H' + R of the first
    measurement is 0 and singular, and Q > 0, else two exact measurements fix position and
    velocity, the predicted P becomes 0 and S is singular from the third measurement on.
    """

    dt_s: float = 1.0
    meas_var_m2: float = (1e-4 * METRES_PER_DEGREE) ** 2
    accel_var_m2_s4: float = 1.0
    init_var: float = 1000.0
    maneuver_accel_var_m2_s4: float = 16.0

    def __post_init__(self) -> None:
        _check("dt_s", self.dt_s, MIN_DT_S <= self.dt_s <= MAX_DT_S, f"in [{MIN_DT_S:g}, {MAX_DT_S:g}] s")
        _variance("maneuver_accel_var_m2_s4", self.maneuver_accel_var_m2_s4)
        _variance("meas_var_m2 (R)", self.meas_var_m2)
        _variance("accel_var_m2_s4 (Q)", self.accel_var_m2_s4)
        _variance("init_var (P0)", self.init_var)
        if self.meas_var_m2 == 0 and self.init_var == 0:
            raise _refuse("meas_var_m2 (R)=0 with init_var (P0)=0: the innovation covariance S = P + R of the first "
                          "measurement would be 0, a singular matrix; give R or P0 a value > 0",
                          "meas_var_m2", "init_var")
        if self.meas_var_m2 == 0 and self.accel_var_m2_s4 == 0:
            raise _refuse("meas_var_m2 (R)=0 with accel_var_m2_s4 (Q)=0: after two exact measurements the predicted "
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
PAPER_MATCH = MatchParams(tau1=0.8, tau2=0.97)
PAPER_RETRIEVAL = RetrievalParams(window_s=20.0, exclusion_s=0.0)
PAPER_EVAL_RETRIEVAL = RetrievalParams(window_s=20.0, exclusion_s=1.0)
PAPER_FILTER = FilterParams(dt_s=1.0, meas_var_m2=(1e-4 * METRES_PER_DEGREE) ** 2, accel_var_m2_s4=1.0, init_var=1000.0)


# -- beyond the paper ------------------------------------------------------------------

@dataclass(frozen=True)
class RefinedParams(_Params):
    """Metric position from the geotagged database (the refined mode), and the filter's gating.

    Verification and structure
      top_k:                 candidates (by correspondence count) verified by two-view geometry
      ratio:                 Lowe ratio of the geometric matching (equation (1) alone: the paper's
                             cosine test, equation (2), rejects too many true matches for geometry)
      essential_px:          RANSAC threshold of the essential matrix, pixels
      min_verified_inliers:  a candidate needs this many essential-matrix inliers to count as verified
      n_views:               verified candidates the query is posed against, chosen on both sides of
                             the query where the database has both (best first otherwise)
      neighbour_baselines_m: a view's structure comes from triangulating it with database images
                             before and after it at about these distances from it, metres (those the
                             retrieval allows, posed, at least ``min_baseline_m`` away)
      max_neighbour_gap:     ... and at most this many frames from it
      min_baseline_m:        a neighbour must be at least this far from the view (else: stopped car)
      triangulation_px:      largest reprojection error of a triangulated point, pixels
      min_parallax_deg:      smallest angle between the two rays of a triangulated point
      max_depth_m:           farthest triangulated point kept, metres
      refine_poses:          before triangulating, refine the poses of the view and its neighbours by bundle
                             adjustment (``visloc.bundle``), with priors that keep each pose near its geotag
                             and attitude: a GNSS/INS attitude can be a degree off where the GPS is not fixed or
                             the car turns, and a structure built on it is bent accordingly
      relative_geotag_sigma_m: the position prior of a pose in that adjustment: how well neighbouring geotags
                             agree with each other over a few metres, per axis (a GNSS/INS track is smooth to
                             centimetres where its absolute error is decimetres: the structure lives in the
                             track's frame, as the query's truth does); where the images move the poses much
                             farther, the prior is loosened to what they moved, metres
      attitude_prior_per_heading_spread: the attitude prior is this many times the database's heading
                             spread (how far its headings stray from its course over ground,
                             ``visloc.bundle.heading_spread_rad``): the spread sees the heading only, about
                             the course, where roll, pitch and a turn's slip add to what a pose can be off
      min_attitude_prior_deg: ... and never tighter than this, degrees
    Pose
      pnp_px:                PnP RANSAC inlier threshold, pixels
      pnp_iterations:        PnP RANSAC iterations
      min_pnp_inliers:       fewer inliers than this: fall back to the geotag
      max_offset_m:          a pose farther than this from the geotag of the view it was solved
                             against is rejected (it cannot see the same scene)
      max_view_spread_m:     the query is also posed against each view alone; a view whose pose lies
                             farther than this from the others' is dropped, and a measurement whose
                             remaining views still disagree by more is rejected
      max_heading_diff_deg:  a pose facing more than this away from its views is rejected
    Uncertainty and filter
      geotag_sigma_m:        standard deviation per axis of a database geotag whose source states no
                             accuracy (a CSV drive without an accuracy column), metres; stated
                             accuracies (OXTS ``pos_accuracy``) are used as they are
      gate_chi2:             a measurement whose squared Mahalanobis distance to the prediction
                             exceeds this is not applied (2 degrees of freedom; 13.82 = 99.9 %);
                             0 disables gating
      reinit_after_gated:    this many gated measurements in a row restart the track at the last of
                             them (the measurements agree with each other, not with the track);
                             0 never restarts
      seed:                  seed of every RANSAC
    """

    top_k: int = 8
    ratio: float = 0.8
    essential_px: float = 1.0
    min_verified_inliers: int = 20
    n_views: int = 2
    both_sides: bool = True
    neighbour_baselines_m: tuple[float, ...] = (2.0, 5.0, 10.0)
    max_neighbour_gap: int = 50
    min_baseline_m: float = 1.0
    triangulation_px: float = 1.0
    min_parallax_deg: float = 0.5
    max_depth_m: float = 80.0
    refine_poses: bool = True
    relative_geotag_sigma_m: float = 0.05
    attitude_prior_per_heading_spread: float = 2.0
    min_attitude_prior_deg: float = 0.2
    pnp_px: float = 2.0
    pnp_iterations: int = 1000
    min_pnp_inliers: int = 15
    max_offset_m: float = 30.0
    max_view_spread_m: float = 1.5
    max_heading_diff_deg: float = 45.0
    geotag_sigma_m: float = 1.0
    gate_chi2: float = 13.82
    reinit_after_gated: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        def integer(name: str, low: int) -> None:
            v = getattr(self, name)
            _check(name, v, isinstance(v, int) and not isinstance(v, bool) and v >= low, f"an integer >= {low}")

        integer("top_k", 1)
        integer("min_verified_inliers", 5)
        integer("n_views", 1)
        integer("max_neighbour_gap", 1)
        baselines = self.neighbour_baselines_m
        if not (isinstance(baselines, tuple) and baselines and all(
                isinstance(b, (int, float)) and math.isfinite(b) and b > 0 for b in baselines)):
            raise ParameterError(f"neighbour_baselines_m={baselines!r}: must be a non-empty tuple of distances > 0")
        integer("pnp_iterations", 1)
        integer("min_pnp_inliers", 6)
        integer("reinit_after_gated", 0)
        _check("seed", self.seed, isinstance(self.seed, int) and not isinstance(self.seed, bool)
               and 0 <= self.seed <= MAX_C_INT, f"an integer in [0, {MAX_C_INT}]")  # OpenCV's RNG seed is a C int
        _check("ratio", self.ratio, 0 < self.ratio <= 1, "in (0, 1]")
        for name in ("essential_px", "triangulation_px", "pnp_px", "max_depth_m", "max_offset_m",
                     "max_view_spread_m", "max_heading_diff_deg"):
            _check(name, getattr(self, name), getattr(self, name) > 0, "> 0")
        if not isinstance(self.refine_poses, bool):
            raise ParameterError(f"refine_poses={self.refine_poses!r}: must be True or False")
        for name in ("relative_geotag_sigma_m", "attitude_prior_per_heading_spread", "min_attitude_prior_deg"):
            _check(name, getattr(self, name), getattr(self, name) > 0, "> 0")
        for name in ("min_baseline_m", "min_parallax_deg", "gate_chi2"):
            _check(name, getattr(self, name), getattr(self, name) >= 0, ">= 0")
        _check("geotag_sigma_m", self.geotag_sigma_m, 0 <= self.geotag_sigma_m <= MAX_GEOTAG_SIGMA_M,
               f"in [0, {MAX_GEOTAG_SIGMA_M:g}] m")  # its square is a measurement variance


REFINED = RefinedParams()

NN_BACKENDS = ("gemm", "faiss", "batched")


@dataclass(frozen=True)
class FastParams(_Params):
    """The fast retrieval: the filter's gate, a global-vector shortlist, exact counts on the shortlist.

    gate_sigmas:        gate radius in standard deviations of the predicted position (largest axis)
    gate_min_radius_m:  the gate is never narrower than this, metres
    shortlist_size:     candidates matched exactly, the most similar by global vector (0 = all in the gate)
    lost_shortlist_size: the same for a query without a usable gate (first query, lost track, empty
                        gate), which searches every allowed image; 0: ``shortlist_size``
    nn_backend:         exact nearest-two search: "batched" (every shortlisted image in one GEMM),
                        "faiss" or "gemm" (numpy float32 GEMM per image, the paper path's)
    n_words:            k-means words of the VLAD codebook
    pca_dim:            dimension of the global vectors after PCA (0 = no PCA, n_words * 128)
    train_descriptors:  descriptors sampled from the database to train the codebook
    seed:               seed of sampling, k-means and PCA
    """

    gate_sigmas: float = 3.0
    gate_min_radius_m: float = 20.0
    shortlist_size: int = 8
    lost_shortlist_size: int = 0
    nn_backend: str = "batched"
    n_words: int = 32
    pca_dim: int = 0
    train_descriptors: int = 100_000
    seed: int = 0

    def __post_init__(self) -> None:
        _check("gate_sigmas", self.gate_sigmas, self.gate_sigmas > 0, "> 0")
        _check("gate_min_radius_m", self.gate_min_radius_m, self.gate_min_radius_m >= 0, ">= 0")
        for name, low in (("shortlist_size", 0), ("lost_shortlist_size", 0), ("n_words", 1), ("pca_dim", 0), ("train_descriptors", 1),
                          ("seed", 0)):
            v = getattr(self, name)
            _check(name, v, isinstance(v, int) and not isinstance(v, bool) and v >= low, f"an integer >= {low}")
        if self.nn_backend not in NN_BACKENDS:
            raise ParameterError(f"nn_backend={self.nn_backend!r}: must be one of {', '.join(NN_BACKENDS)}")


FAST = FastParams()


@dataclass(frozen=True)
class TrackParams(_Params):
    """A continuous run: every frame of a drive in order, at the camera's rate.

    fast:              True: the camera-rate refined path (``visloc.fastpose``: stored structure, the
                       filter's gate, a global-vector shortlist, matching against 3D points only).
                       False: the exact refined path (the paper's retrieval, every candidate verified)
    query_image_scale: fast path: SIFT runs on the query image resized by this factor (the database
                       keeps its own, full-resolution features and structure)
    query_max_keypoints: fast path: SIFT keeps at most this many keypoints of a frame, the strongest
                       (0: all)
    shortlist_size:    fast path: candidates matched per frame, the most similar by global vector
                       inside the filter's gate
    lost_shortlist_size: fast path: the same for a frame without a usable gate (the first frame, a lost
                       track), which looks at every allowed image
    min_matches:       fast path: a candidate needs this many matches to its 3D points to be posed against
    pnp_px:            fast path: PnP inlier threshold, pixels (keypoints found at a reduced scale are
                       less precise than the exact path's full-resolution ones)
    exclusion_s:       database images closer in time to the frame than this are not used (0: off; use
                       it when the database is the queries' own camera)
    stride:            localize every stride-th frame (1: every frame); the filter's time step follows
    """

    fast: bool = True
    query_image_scale: float = 0.75
    query_max_keypoints: int = 1500
    shortlist_size: int = 3
    lost_shortlist_size: int = 16
    min_matches: int = 20
    pnp_px: float = 3.0
    exclusion_s: float = 0.0
    stride: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.fast, bool):
            raise ParameterError(f"fast={self.fast!r}: must be True or False")
        _check("query_image_scale", self.query_image_scale, 0.1 <= self.query_image_scale <= 1, "in [0.1, 1]")
        for name, low in (("query_max_keypoints", 0), ("shortlist_size", 1), ("lost_shortlist_size", 1),
                          ("min_matches", 6), ("stride", 1)):
            v = getattr(self, name)
            _check(name, v, isinstance(v, int) and not isinstance(v, bool) and v >= low, f"an integer >= {low}")
        _check("query_max_keypoints", self.query_max_keypoints, self.query_max_keypoints <= MAX_C_INT,
               f"an integer in [0, {MAX_C_INT}]")
        _check("pnp_px", self.pnp_px, self.pnp_px > 0, "> 0")
        _check("exclusion_s", self.exclusion_s, 0 <= self.exclusion_s <= MAX_SECONDS, f"in [0, {MAX_SECONDS:g}]")


TRACK = TrackParams()
