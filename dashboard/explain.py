"""Words for a first-time user: the controls' hover hints, what each row of the step table means,
and the help fold ("What am I looking at?"). Plain strings and one pure function; no viser here.
"""

from __future__ import annotations

# hover hints of the controls, by handle name (see visloc.dashboard.gui); a parameter's control has its hint
# where the parameter is declared (visloc.params)
HINTS = {
    "step": "Which query of the drive run is shown (1 = the first). The table, plots, map, 3D view and images "
            "all follow it",
    "prev_next": "One query back or forward",
    "play": "Step through the run by itself",
    "speed": "1x: one step per query interval, as the car drove",
    "follow": "Keep the 3D view on the current estimate, framing its 2σ ellipse",
    "latlon": "Also show latitude and longitude (WGS84, degrees) beside the local east/north metres",
    "mode": "paper: the measurement is the best-matching database image's geotag. refined: a metric pose "
            "solved from the database's own geometry (PnP), the geotag only as fallback. refined-fast: the same "
            "pose at camera rate, on the 3D points stored at ingest, following them between relocalizations "
            "on the drive's images as visloc track does (it starts at 10 Hz: press Play)",
    "rate": "One query every 1/rate s; also the filter's time step Δt. Choosing a mode moves it to the mode's "
            "own (10 Hz for refined-fast, 1 Hz for the others) unless another rate was chosen",
    "start": "Time after the first frame (s) where the run starts",
    "reset": "τ1 0.8, τ2 0.97, R 0.0001° (11.12 m), P0 1000·I, 1 Hz, paper mode",
    "store": "The store file (built by 'visloc ingest') the page reads; it is never changed",
    "store_path": "Path of another store file, then press Open",
    "db": "The image series searched (its geotags are the database)",
    "queries": "The image series localized, one query at a time",
    "geojson": "The current run's ground truth, measurements and estimates (with 2σ ellipses) as a GeoJSON "
               "file for GIS tools",
    "csv": "The current run, one row per step: truth, measurement, estimate, covariance (m²), errors (m)",
    "mcap": "The current run as an MCAP file for Foxglove: location fixes with their covariance (Map panel), the "
            "tracks and 2σ ellipses as 3D scene entities (3D panel, frame visloc_local), each step's figures",
}

# the step table's rows: what each means (shown on hover and in the help fold)
TERMS = {
    "query": "The camera image being localized at this step, and its time since the first frame",
    "best match": "The allowed database image with the most correspondences to the query",
    "correspondences": "Query features whose nearest database feature passes both tests (τ1 and τ2)",
    "candidates": "Database images compared with the query at this step (the search window, minus the "
                  "exclusion)",
    "measurement": "Where this step's measurement puts the car (east, north in metres from the database's "
                   "origin)",
    "measured by": "paper mode: the geotag of the best match. refined modes: PnP, the camera pose solved from "
                   "3D points that the best database views were triangulated into with their neighbours; "
                   "inliers are the correspondences that agree with that pose",
    "measurement error": "Distance from the measurement to the ground truth (m)",
    "measurement σ": "The measurement's own uncertainty (m), along its most uncertain direction: the filter's R "
                     "for a geotag; for a pose, relative to the map: the PnP fit, the disagreement of its views, "
                     "and what the database's poses get wrong over the distance to the nearest view (grows "
                     "faster when every view lies on one side). Its 2σ ellipse is drawn light orange",
    "map's own error": "How far the database's geotags themselves may be off (their stated accuracy, m per "
                       "axis): an error every step shares, so the filter cannot average it away; it is not in "
                       "the ellipses, which are relative to the map",
    "estimate": "The Kalman filter's position after this step",
    "estimate error": "Distance from the estimate to the ground truth (m)",
    "estimate 2σ": "Twice the filter's standard deviation along its most uncertain direction (m), from its "
                   "covariance P (the blue ellipses): the truth should lie inside the 2σ ellipse about 86 % of "
                   "the time",
    "nearest allowed image": "The smallest error any allowed database image's geotag could give (m): the "
                             "floor of the paper's method at this step",
    "truth": "The query's recorded GPS/IMU position (ground truth)",
    "τ1, τ2": "The two tests a feature pair must pass to count as a correspondence: Lowe's ratio (τ1, lower "
              "is stricter; equation 1: d1²/d2² < τ1²) and cosine similarity (τ2, higher is stricter; equation 2). "
              "The camera-rate mode (refined-fast) uses neither",
    "R, Q, P0": "The Kalman filter's measurement noise (m), acceleration noise (m/s²) and initial uncertainty "
                "(m, m/s); changing them re-runs only the filter",
    "gate": "Refined modes: a measurement whose squared Mahalanobis distance to the filter's prediction "
            "exceeds the gate χ² is skipped, and that step only predicts",
}


def help_html() -> str:
    """The help fold: what the page shows, the colours, and the terms."""
    terms = "".join(f"<li><b>{name}</b>: {meaning}</li>" for name, meaning in TERMS.items())
    return (
        '<div style="font-size:12.5px;line-height:1.45;padding:0 4px">'
        "<p style=\"margin:4px 0\">A car drove with a camera. Each <b>query</b> image is compared with a "
        "<b>database</b> of geotagged images of the same road; the best-matching image gives a "
        "<b>measurement</b> of where the car is, and a Kalman filter smooths the measurements into an "
        "<b>estimate</b> with an uncertainty (the <b>2σ ellipse</b>). The <b>ground truth</b> is the car's "
        "recorded GPS.</p>"
        "<p style=\"margin:4px 0\"><b>3D view</b> (middle) and <b>Map</b> tab (top-down, north up): green = "
        "truth, orange = measurements (light orange: a refined measurement's own 2σ ellipse), blue = "
        "estimates and their 2σ ellipses (the filter's covariance), grey = database images, "
        "magenta = the current step. <b>Current step</b> tab: the query above its best match with "
        "correspondences joined, the step's numbers, the correspondences per database image, and the "
        "error per step.</p>"
        "<p style=\"margin:4px 0\">Positions are east and north in metres from the database's origin (its "
        "first image's geotag). <b>Matching</b> controls re-match every query in the background; "
        "<b>Filter</b> controls only re-run the filter (instant). All open tabs share one session.</p>"
        f'<ul style="margin:4px 0;padding-left:16px">{terms}</ul></div>')
