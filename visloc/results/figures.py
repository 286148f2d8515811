"""Pictures computed from arrays: the paper's Figure 3 (correspondences between two images).

Pure functions over numpy arrays returning RGB uint8 images; callers decide where
they go (a PNG, a dashboard panel).
"""

from __future__ import annotations

import cv2
import numpy as np


def _to_rgb(gray_or_rgb: np.ndarray) -> np.ndarray:
    img = np.asarray(gray_or_rgb)
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    return img.copy()


def correspondence_figure(query_image: np.ndarray, db_image: np.ndarray, query_xy_px: np.ndarray,
                          db_xy_px: np.ndarray, *, max_lines: int = 150, labels: tuple[str, str] = ("", ""),
                          width_px: int | None = None, seed: int = 0) -> np.ndarray:
    """The query image above the database image, corresponding keypoints joined by lines.

    query_xy_px, db_xy_px: (M, 2) pixel positions of the M correspondences, row k of
    one matching row k of the other. At most ``max_lines`` are drawn, an even sample
    (seeded) when there are more. ``width_px`` rescales the figure. Returns (H, W, 3) RGB.
    """
    top, bottom = _to_rgb(query_image), _to_rgb(db_image)
    q = np.asarray(query_xy_px, float).reshape(-1, 2)
    d = np.asarray(db_xy_px, float).reshape(-1, 2)
    if q.shape != d.shape:
        raise ValueError(f"query and database points differ in shape: {q.shape} vs {d.shape}")
    width = max(top.shape[1], bottom.shape[1])
    canvas = np.full((top.shape[0] + bottom.shape[0], width, 3), 255, np.uint8)
    canvas[: top.shape[0], : top.shape[1]] = top
    canvas[top.shape[0]:, : bottom.shape[1]] = bottom
    scale = 1.0 if width_px is None else width_px / width
    if scale != 1.0:
        canvas = cv2.resize(canvas, (int(round(width * scale)), int(round(canvas.shape[0] * scale))),
                            interpolation=cv2.INTER_AREA)
    rng = np.random.default_rng(seed)
    keep = np.arange(len(q))
    if len(keep) > max_lines:
        keep = np.sort(rng.choice(keep, max_lines, replace=False))
    hues = rng.integers(0, 180, len(keep))
    colors = cv2.cvtColor(np.stack([hues, np.full_like(hues, 220), np.full_like(hues, 255)], axis=1)
                          .astype(np.uint8)[None], cv2.COLOR_HSV2RGB)[0]
    shift = 4  # sub-pixel drawing
    for (xq, yq), (xd, yd), color in zip(q[keep] * scale, (d[keep] + [0, top.shape[0]]) * scale, colors):
        p1 = (int(round(xq * (1 << shift))), int(round(yq * (1 << shift))))
        p2 = (int(round(xd * (1 << shift))), int(round(yd * (1 << shift))))
        c = tuple(int(v) for v in color)
        cv2.line(canvas, p1, p2, c, 1, cv2.LINE_AA, shift)
        cv2.circle(canvas, p1, 2 << shift, c, 1, cv2.LINE_AA, shift)
        cv2.circle(canvas, p2, 2 << shift, c, 1, cv2.LINE_AA, shift)
    for text, y in zip(labels, (0, int(round(top.shape[0] * scale)))):
        if text:
            (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
            cv2.rectangle(canvas, (0, y), (tw + 8, y + th + 10), (0, 0, 0), -1)
            cv2.putText(canvas, text, (4, y + th + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas
