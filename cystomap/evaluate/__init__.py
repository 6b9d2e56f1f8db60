"""Score cystomap's outputs against the bladder phantom's ground truth.

Truth (one directory per session): ``poses.csv`` (frame, qw, qx, qy, qz, tx, ty, tz:
camera-to-world rotation and camera centre, mm, OpenCV axes), ``camera.json``, ``surface.ply``,
``seen.png`` and ``albedo.png`` (equirectangular about the barycentre: column → azimuth
−180°…+180°, row → elevation +90°…−90°, pixel centres), ``lesions.csv`` and ``truth.json``
(n_frames, barycentre, extent_mm, area_mm2, seen_fraction, bad_frames).

Scored outputs, all optional: COLMAP models (image names carry the frame index), the mesh
``surface.ply`` and ``atlas.json``/``atlas.png`` in the model frame, and ``changes.csv`` of a
comparison in session B's model frame. A Sim(3) fitted on the camera centres (Umeyama) takes
each model into the truth frame.
"""

from cystomap.evaluate.config import EvalConfig
from cystomap.evaluate.lesions import match_lesions, score_changes
from cystomap.evaluate.session import (
    ComparisonInputs,
    SessionInputs,
    comparisons_from_lists,
    evaluate_changes,
    evaluate_session,
    evaluate_subject,
    flatten,
    sessions_from_lists,
)
from cystomap.evaluate.surface import score_atlas, score_surface
from cystomap.evaluate.trajectory import Sim3, align, load_model, umeyama
from cystomap.evaluate.truth import Truth, load_truth

__all__ = [
    "ComparisonInputs",
    "EvalConfig",
    "SessionInputs",
    "Sim3",
    "Truth",
    "align",
    "comparisons_from_lists",
    "evaluate_changes",
    "evaluate_session",
    "evaluate_subject",
    "flatten",
    "load_model",
    "load_truth",
    "match_lesions",
    "score_atlas",
    "score_changes",
    "score_surface",
    "sessions_from_lists",
    "umeyama",
]
