"""Parameters beyond the paper: the refined measurement and the filter's gate, the fast retrieval, and a
continuous run at the camera's rate. Every field is declared once (``visloc.params.declare``)."""

from __future__ import annotations

from dataclasses import dataclass

from visloc.params.declare import MAX_C_INT, Control, Params, param
from visloc.params.paper import MAX_GEOTAG_SIGMA_M, MAX_SECONDS
from visloc.stats import CHI2_2DOF_999

REFINED_BOTH = ("refined", "refined-fast")
FAST_RETRIEVAL = ("refined-fast", "--fast")


def _refined(default, help: str, **spec):
    return param(default, help, methods=REFINED_BOTH, **spec)


@dataclass(frozen=True)
class RefinedParams(Params):
    """Metric position from the geotagged database (the refined mode), and the filter's gating.

    Verification, then structure triangulated from each verified view and its neighbours (poses
    refined by bundle adjustment with priors first, ``visloc.geometry.bundle``), then PnP; its uncertainty;
    the filter's gate. The camera-rate path reads the structure stored at ingest, made with these.
    """

    top_k: int = _refined(8, "candidates (by correspondence count) verified by two-view geometry",
                          kind="integer", low=1)
    ratio: float = _refined(0.8, "Lowe ratio of the geometric matching (equation (1) alone: the paper's cosine "
                                 "test rejects too many true matches for geometry)", low=0, high=1, open_low=True)
    essential_px: float = _refined(1.0, "RANSAC threshold of the essential matrix", unit="px", low=0, open_low=True)
    min_verified_inliers: int = _refined(20, "essential-matrix inliers a candidate needs to count as verified",
                                         kind="integer", low=5)
    n_views: int = _refined(6, "verified candidates the query is posed against, each alone (refined-fast: 2, for "
                               "its latency)", kind="integer", low=1)
    both_sides: bool = _refined(True, "choose the views on both sides of the query where the database has both "
                                      "(best first otherwise)", kind="bool")
    other_side_candidates: int = _refined(
        2, "where every view lies on one side of the query's pose and no verified candidate on the other, this many "
           "allowed database images nearest the pose on the other side are verified too, and the query "
           "posed again with them: the retrieval's best candidates often all lie ahead of a fast car, while the "
           "images behind it see the same scene (0: never; refined-fast does not search)", kind="integer", low=0)
    other_side_max_turn_deg: float = _refined(
        15.0, "... facing at most this far from the query's heading: in a turn, an image behind the car looks across "
              "the scene the views ahead see, and posed from both the query is no better placed", unit="deg", low=0,
        open_low=True)
    fuse_views: bool = _refined(
        True, "pose the query against each view alone (its own RANSAC and guided matching) and average the views' "
              "positions; off: one PnP over every view's points. Each view's structure is adjusted on its own, and where "
              "geotags disagree by more than the PnP threshold (float GPS) one PnP keeps only the views that agree, "
              "often those on one side",
        kind="bool")
    neighbour_baselines_m: tuple[float, ...] = _refined(
        (2.0, 5.0, 10.0),
        "a view's structure comes from triangulating it with database images before and after it at about these "
        "distances (comma-separated); more neighbours, and nearer ones, give more of its keypoints a point",
        unit="m", kind="distances")
    max_neighbour_gap: int = _refined(50, "... and at most this many frames from it", kind="integer", low=1)
    min_baseline_m: float = _refined(1.0, "a neighbour must be at least this far from the view (else: a stopped car)",
                                     unit="m", low=0)
    triangulation_px: float = _refined(1.0, "largest reprojection error of a triangulated point", unit="px", low=0,
                                       open_low=True)
    min_parallax_deg: float = _refined(0.5, "smallest angle between the two rays of a triangulated point",
                                       unit="deg", low=0)
    max_depth_m: float = _refined(80.0, "farthest triangulated point kept", unit="m", low=0, open_low=True)
    refine_poses: bool = _refined(True, "before triangulating, refine the poses of the view and its neighbours by "
                                        "bundle adjustment, with priors that keep each near its geotag and attitude",
                                  kind="bool")
    max_adjusted_points: int = _refined(0, "... on at most this many of the view's points, those most neighbours see "
                                           "(0: all; a few hundred cut the cost of many neighbours)", kind="integer",
                                        low=0)
    relative_geotag_sigma_m: float = _refined(
        0.005, "position prior of a pose in that adjustment: how well neighbouring geotags agree with each other over "
              "a few metres, per axis (loosened where the images move the poses farther)",
        unit="m", low=0, open_low=True)
    attitude_prior_per_heading_spread: float = _refined(
        2.0, "the attitude prior is this many times the database's heading spread (how far its headings stray from "
             "its course over ground)", low=0, open_low=True)
    min_attitude_prior_deg: float = _refined(0.2, "... and never tighter than this", unit="deg", low=0, open_low=True)
    pnp_px: float = _refined(2.0, "PnP RANSAC inlier threshold (refined-fast: 3, for keypoints found at a reduced "
                                  "scale)", unit="px", low=0, open_low=True)
    guided_radius_px: float = _refined(
        4.0, "once posed, each view's 3D points are projected into the query and matched to the query keypoints "
             "within this distance of where they land, and the query posed again on both (0: no guided matching; "
             "refined-fast: 0, for its latency)",
        unit="px", low=0)
    guided_ratio: float = _refined(0.9, "Lowe ratio among the query keypoints near a projected point",
                                   low=0, high=1, open_low=True)
    pnp_iterations: int = _refined(1000, "PnP RANSAC iterations", kind="integer", low=1)
    min_pnp_inliers: int = _refined(15, "fewer PnP inliers than this: fall back to the geotag", kind="integer", low=6)
    thin_support_pnp_px: float = _refined(
        4.0, "where support is thin (no pose reaches min_pnp_inliers at pnp_px: little texture, few keypoints), the "
             "query is posed again at this PnP threshold before falling back to the geotag; the pose's covariance "
             "comes from its own residuals, so a looser pose says it is looser (0: never)", unit="px", low=0)
    thin_support_min_inliers: int = _refined(10, "... needing this many PnP inliers", kind="integer", low=6)
    max_offset_m: float = _refined(30.0, "a pose farther than this from the geotag of the view it was solved against "
                                         "is rejected", unit="m", low=0, open_low=True)
    max_view_spread_m: float = _refined(
        1.5, "the query is also posed against each view alone; a view whose pose lies farther than this from the "
             "others' is dropped; where the views still disagree by more, those within half of it of their median "
             "are kept if they are most of them (views posed apart), and the measurement is rejected otherwise",
        unit="m", low=0, open_low=True)
    max_heading_diff_deg: float = _refined(45.0, "a pose facing more than this away from its views is rejected",
                                           unit="deg", low=0, open_low=True)
    geotag_sigma_m: float = _refined(
        1.0, "accuracy (standard deviation per axis) assumed for database geotags whose source states none; stated "
             "accuracies (OXTS pos_accuracy, a CSV's accuracy_m) are used as they are. Where a drive states the "
             "others', a geotag that states none (an OXTS record with no position solution) is no fix of the "
             "receiver, and the structure built on it carries this error into the measurement's covariance",
        unit="m", low=0, high=MAX_GEOTAG_SIGMA_M)
    gate_chi2: float = _refined(
        CHI2_2DOF_999, "a measurement whose squared Mahalanobis distance y' S^-1 y to the prediction exceeds this is not "
               "applied (2 degrees of freedom; 13.82 = 99.9 %); 0 disables gating", low=0,
        control=Control("Gate χ² (refined)", 0.0, 50.0, 0.01, "filter",
                        hint="Refined modes only: a measurement whose squared Mahalanobis distance to the filter's "
                             "prediction exceeds this is skipped (the step only predicts). 13.82 = 99.9 % for 2 "
                             "degrees of freedom; 0 = off. Unitless"))
    reinit_after_gated: int = _refined(2, "this many gated measurements in a row restart the track at the last of "
                                          "them; 0 never restarts", kind="integer", low=0)
    error_correlation: float = _refined(
        0.57, "share of a pose measurement's covariance that its error shares with the measurements just before "
              "and after it (the same views, the same structure): the filter then does not take ten measurements "
              "a second for ten independent ones; 0 takes every measurement as independent (measured by "
              "benchmarks/measurement_correlation.py)", low=0, high=0.99)
    error_correlation_time_s: float = _refined(
        0.72, "how fast that shared error fades: measurements dt apart share error_correlation * exp(-dt / this) "
              "of their errors (measured by benchmarks/measurement_correlation.py)", unit="s", low=0, open_low=True,
        high=MAX_SECONDS)
    seed: int = _refined(0, "seed of every RANSAC", kind="integer", low=0, high=MAX_C_INT)


REFINED = RefinedParams()

NN_BACKENDS = ("gemm", "faiss", "batched")
_CODEBOOK = "set when the store's global vectors are built; not a query-time setting"


@dataclass(frozen=True)
class FastParams(Params):
    """The fast retrieval: the filter's gate, a global-vector (VLAD) shortlist, exact counts on the
    shortlist. Used by ``--fast`` and by the camera-rate method (refined-fast)."""

    gate_sigmas: float = param(3.0, "gate radius in standard deviations of the predicted position (largest axis)",
                               low=0, open_low=True, methods=FAST_RETRIEVAL)
    gate_min_radius_m: float = param(20.0, "the gate is never narrower than this", unit="m", low=0,
                                     methods=FAST_RETRIEVAL)
    shortlist_size: int = param(8, "candidates matched exactly, the most similar by global vector inside the gate "
                                   "(0: all in the gate)", kind="integer", low=0, methods=FAST_RETRIEVAL,
                                flag="--shortlist")
    lost_shortlist_size: int = param(0, "the same for a query without a usable gate (first query, lost track), which "
                                        "searches every allowed image; 0: --shortlist", kind="integer", low=0,
                                     methods=FAST_RETRIEVAL, flag="--lost-shortlist")
    nn_backend: str = param("batched", "exact nearest-two search: batched (every shortlisted image in one GEMM), "
                                       "faiss, or gemm (per image, the paper path's)", kind="choice",
                            choices=NN_BACKENDS, methods=FAST_RETRIEVAL)
    n_words: int = param(32, "k-means words of the VLAD codebook; " + _CODEBOOK, kind="integer", low=1,
                         methods=FAST_RETRIEVAL, flag=None)
    pca_dim: int = param(0, "dimension of the global vectors after PCA (0: no PCA); " + _CODEBOOK, kind="integer",
                         low=0, methods=FAST_RETRIEVAL, flag=None)
    train_descriptors: int = param(100_000, "descriptors sampled from the database to train the codebook; "
                                   + _CODEBOOK, kind="integer", low=1, methods=FAST_RETRIEVAL, flag=None)
    seed: int = param(0, "seed of sampling, k-means and PCA; " + _CODEBOOK, kind="integer", low=0,
                      methods=FAST_RETRIEVAL, flag=None)


FAST = FastParams()

TRACK_ONLY = ("track",)


@dataclass(frozen=True)
class TrackParams(Params):
    """A continuous run: every frame of a drive in order, at the camera's rate. The method's own
    settings (shortlist, PnP threshold) are the refined-fast preset's (``visloc.tracking.methods``)."""

    fast: bool = param(True, "the camera-rate refined path (stored structure, the filter's gate, a global-vector "
                             "shortlist, matching against 3D points only); False: the exact refined path (--exact)",
                       kind="bool", methods=TRACK_ONLY, flag=None)
    query_image_scale: float = param(0.75, "camera-rate path: SIFT runs on the frame resized by this factor (the "
                                           "database keeps its full-resolution features and structure)",
                                     low=0.1, high=1, methods=TRACK_ONLY, flag="--query-scale")
    query_max_keypoints: int = param(1500, "camera-rate path: SIFT keeps at most this many keypoints of a frame, the "
                                           "strongest (0: all)", kind="integer", low=0, high=MAX_C_INT,
                                     methods=TRACK_ONLY, flag="--query-keypoints")
    exclusion_s: float = param(0.0, "database images closer in time to the frame than this are not used (0: off)",
                               unit="s", low=0, high=MAX_SECONDS, methods=TRACK_ONLY)
    stride: int = param(1, "localize every stride-th frame (1: every frame); the filter's time step follows",
                        kind="integer", low=1, methods=TRACK_ONLY)
    follow_points: bool | None = param(None, "between relocalizations, follow the last posed frame's map "
                                             "points by optical flow and pose each frame against them: read as "
                                             "each relocalization keeps up (the default), as accurate as "
                                             "localizing every frame in full (--no-follow-points) on the shared "
                                             "drives; at the camera's 10 Hz (--pace-hz 10) as well, on about half "
                                             "its processor (docs/performance.md); read as fast as possible "
                                             "(--pace-hz 0), far less accurate, as the relocalizations fall behind",
                                       kind="bool", methods=TRACK_ONLY,
                                       when_unset="on the camera-rate path at every frame (--stride 1), off on the exact "
                                                  "one (--exact): points are followed from one frame to the next")
    relocalize_every: int = param(4, "following points: relocalize at least every this many frames, to "
                                     "find new map points on the nearest views (0: only when the followed ones no "
                                     "longer serve)",
                                  kind="integer", low=0, high=MAX_C_INT, methods=TRACK_ONLY)
    relocalize_behind_only_every: int = param(2, "following points: a frame posed on views behind it only (none "
                                                 "ahead along the camera's axis) relocalizes once this many "
                                                 "frames have passed since the last relocalization: the views "
                                                 "ahead leave the exclusion window a frame or two after they are "
                                                 "handed on, and a pose on one side's views repeats that side's "
                                                 "bias frame after frame (0: only as --relocalize-every says)",
                                              kind="integer", low=0, high=MAX_C_INT, methods=TRACK_ONLY)
    min_followed_points: int = param(40, "following points: a frame posed on fewer image tracks (followed keypoints, "
                                         "each once however many views' structure holds its map point) than this: "
                                         "relocalize", kind="integer", low=6, high=MAX_C_INT, methods=TRACK_ONLY)
    min_followed_cells: int = param(4, "following points: points in fewer of the image's 4 x 4 cells than this: "
                                       "relocalize", kind="integer", low=0, high=16, methods=TRACK_ONLY)
    max_followed_lever_m: float = param(15.0, "following points: a frame farther than this from the nearest view "
                                              "its points come from: relocalize", unit="m", low=0.1,
                                        high=1000, methods=TRACK_ONLY)
    max_followed_lever_excess_m: float = param(1.0, "following points: the nearest view of a frame's points farther "
                                                    "than the nearest view it may use by more than this: localize "
                                                    "again, to pose on the nearer views", unit="m", low=0,
                                               high=1000, methods=TRACK_ONLY)
    max_followed_sigma_m: float = param(1.0, "following points: the estimate's 1-sigma larger than this: "
                                             "relocalize", unit="m", low=0.01, high=1000, methods=TRACK_ONLY)
    background_relocalization: bool = param(True, "following points: relocalizations asked for by a tracked "
                                                  "frame run beside the tracker, so no frame waits for one "
                                                  "(--no-background-relocalization: the frame that asks waits; "
                                                  "the run is then reproducible)", kind="bool", methods=TRACK_ONLY)
    guided_relocalization: bool = param(True, "following points: a tracked frame that asks for new points finds "
                                              "them where its pose projects the nearest views' points, SIFT "
                                              "describing only the keypoints there, with no retrieval (the full "
                                              "path when that gives no pose): cheaper, and on the shared drives "
                                              "as accurate as localizing every frame in full "
                                              "(--no-guided-relocalization: every relocalization in full, with "
                                              "retrieval; docs/performance.md)", kind="bool", methods=TRACK_ONLY)
    max_lost_wait_ms: float = param(30.0, "following points, with relocalizations beside the tracker: a frame "
                                          "whose points give no pose waits at most this long for the one under "
                                          "way, then the filter predicts it (0: never waits)", unit="ms", low=0,
                                    high=10000, methods=TRACK_ONLY)
    pace_hz: float | None = param(None, "read frames at this rate, as a live camera delivers them, to measure the "
                                        "share of the processor a live run takes (0: as fast as possible)",
                                  unit="Hz", low=0, high=1000, methods=TRACK_ONLY,
                                  when_unset="following points, as fast as the relocalizations beside the "
                                             "tracker keep up: a frame is read once the one asked for before it "
                                             "has come, as on a vehicle where one takes less than a frame's "
                                             "interval; else as fast as possible")


TRACK = TrackParams()
