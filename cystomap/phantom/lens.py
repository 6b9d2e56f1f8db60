"""The phantom's lens: the camera it renders with (``lens_k1``) and its truth record."""

from __future__ import annotations

import logging
from dataclasses import replace

import cv2
import numpy as np

from cystomap.camera import Camera
from cystomap.phantom.config import PhantomConfig

log = logging.getLogger(__name__)


def render_camera(cfg: PhantomConfig, camera: Camera) -> Camera:
    """The lens the phantom is rendered with: ``camera`` with k1 replaced by ``cfg.lens_k1``
    (when set; the pinhole part, e.g. the focal length of a ``diagonal_fov_deg``-only camera,
    is kept). It is the truth (camera.json), hence calibrated."""
    if cfg.lens_k1 is None:
        return camera
    cam = replace(camera, dist=(float(cfg.lens_k1), *camera.dist[1:]), calibrated=True)
    if camera.calibrated and camera.dist != cam.dist:
        log.warning("phantom: lens_k1 %.4g overrides k1 %.4g of the calibrated camera %r: the"
                    " pipeline is given a calibration that differs from the rendered lens",
                    cfg.lens_k1, camera.dist[0], camera.name)
    return cam


def corner_fov_deg(camera: Camera) -> float:
    """True diagonal field of view (deg): the angle between the rays of two opposite corners."""
    corners = np.array([[-0.5, -0.5], [camera.width - 0.5, camera.height - 0.5]])
    if camera.has_distortion:
        und = cv2.undistortPoints(corners.reshape(-1, 1, 2), camera.K, camera.dist_array,
                                  None, None, None, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                                     100, 1e-14)).reshape(-1, 2)
    else:
        und = (corners - [camera.cx, camera.cy]) / [camera.fx, camera.fy]
    d = np.concatenate([und, np.ones((2, 1))], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return float(np.degrees(np.arccos(np.clip(d[0] @ d[1], -1, 1))))


def lens_truth(cfg: PhantomConfig, given: Camera, rendered: Camera) -> dict:
    """truth.json ``lens``: the rendered lens against the camera the study was given."""
    return {
        "k1_override": cfg.lens_k1,
        "rendered": rendered.to_dict(),
        "given": given.to_dict(),
        "given_is_rendered": given.calibrated and given.dist == rendered.dist
        and given.K.tolist() == rendered.K.tolist(),
        "diagonal_fov_deg_true": round(corner_fov_deg(rendered), 4),
        "note": "camera.json = the rendered lens (OpenCV model); 'given' = the cameras: entry the"
                " pipeline is told (diagonal_fov_deg only: uncalibrated, pinhole guess);"
                " diagonal_fov_deg_true = angle between the rays of opposite image corners",
    }
