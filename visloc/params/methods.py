"""The named methods as parameters: which retriever and which measurer a localizer is made of
(``visloc.tracking.methods`` builds one from a ``Method``). Declared here, beside the parameters they
hold, so that the command line can name and describe them without loading the pipeline.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from visloc.errors import ParameterError
from visloc.params.paper import PAPER_SIFT, SiftParams
from visloc.params.refined import FAST, REFINED, FastParams, RefinedParams


@dataclass(frozen=True)
class Method:
    """A named composition of retriever, measurer and filter gate.

    name:       what reports and the command line call it
    pose:       None: the paper's measurement, the best match's geotag. ``RefinedParams``: a metric
                pose from the database's own geometry (falling back to the geotag with a reason),
                and the filter skips measurements beyond ``pose.gate_chi2`` and models the error they
                share (``filter_options``).
    shortlist:  None: the paper's retrieval. ``FastParams``: the fast retrieval (filter gate,
                global-vector shortlist, exact counts on the shortlist).
    camera_rate: the camera-rate refined path (needs ``pose`` and ``shortlist``): candidates counted
                by their matches to the database's stored structure, posed on it
                (``visloc.pose.fastpose``); ``min_matches`` a candidate needs to be posed against.
    """

    name: str
    pose: RefinedParams | None = None
    shortlist: FastParams | None = None
    camera_rate: bool = False
    min_matches: int = 20

    def __post_init__(self) -> None:
        if not (isinstance(self.name, str) and self.name):
            raise ParameterError(f"name={self.name!r}: a method needs a name")
        if self.camera_rate and (self.pose is None or self.shortlist is None):
            raise ParameterError(f"{self.name}: the camera-rate path needs refined and shortlist parameters")

    @property
    def measures_pose(self) -> bool:
        return self.pose is not None

    @property
    def geotag_sigma_m(self) -> float:
        """The accuracy taken for a geotag that states none: the pose's ``geotag_sigma_m`` (the paper's method,
        which has none of its own: the refined default)."""
        return (self.pose or REFINED).geotag_sigma_m

    @property
    def filter_options(self) -> dict:
        """How the filter reads this method's measurements (``visloc.tracking.kalman.ConstantVelocityKalman``'s
        options): the gate, the restart after gated measurements, and the error two pose measurements share
        (none for the paper's geotags)."""
        if self.pose is None:
            return {"gate_chi2": 0.0, "reinit_after_gated": 0, "corr_fraction": 0.0, "corr_time_s": 1.0}
        return {"gate_chi2": self.pose.gate_chi2, "reinit_after_gated": self.pose.reinit_after_gated,
                "corr_fraction": self.pose.error_correlation, "corr_time_s": self.pose.error_correlation_time_s}

    def replace(self, **changes) -> "Method":
        unknown = set(changes) - {f.name for f in fields(self)}
        if unknown:
            raise ParameterError(f"unknown parameter {sorted(unknown)[0]!r} for Method")
        return replace(self, **changes)

    def as_dict(self) -> dict:
        return {"name": self.name, "pose": None if self.pose is None else self.pose.as_dict(),
                "shortlist": None if self.shortlist is None else self.shortlist.as_dict(),
                "camera_rate": self.camera_rate, "min_matches": self.min_matches}


PAPER_METHOD = Method("paper")
REFINED_METHOD = Method("refined", pose=REFINED)
# the camera-rate path: keypoints found at a reduced scale are less precise (PnP at 3 px); two views and no
# guided matching, for its latency; each view posed alone and the two positions averaged, as the exact path
# does (a view's structure is adjusted on its own poses, so two views' points need not agree with one pose to
# a centimetre: one PnP over both views' points was 0.02-0.2 m worse where their structures disagree); few
# candidates per frame inside the gate, more for a frame without one
REFINED_FAST_METHOD = Method("refined-fast", pose=REFINED.replace(pnp_px=3.0, n_views=2, guided_radius_px=0.0),
                             shortlist=FAST.replace(shortlist_size=3, lost_shortlist_size=16), camera_rate=True,
                             min_matches=20)
METHODS = {m.name: m for m in (PAPER_METHOD, REFINED_METHOD, REFINED_FAST_METHOD)}


def method_named(name: str) -> Method:
    """The method called ``name``; ``ParameterError`` naming the choices otherwise."""
    if name not in METHODS:
        raise ParameterError(f"mode={name!r}: must be one of {', '.join(METHODS)}")
    return METHODS[name]


def features_for(method: Method, store: SiftParams) -> SiftParams:
    """The SIFT settings ``method`` reads a store built with ``store`` at: the store's own, but the paper's
    method (no pose) reads a store built at a lower contrast threshold than the paper's at the paper's, with
    the keypoints SIFT keeps there (``visloc.features.sift.contrast_kept``): its own features."""
    if method.pose is None and store.contrast_threshold < PAPER_SIFT.contrast_threshold:
        return store.replace(contrast_threshold=PAPER_SIFT.contrast_threshold)
    return store
