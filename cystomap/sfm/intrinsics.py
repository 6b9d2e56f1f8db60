"""Self-calibration of an uncalibrated scope: the estimated camera, an undistorted model and
undistorted frames for the later stages.

With only a field-of-view prior, the frames reach the stage as recorded (preprocess cannot
undistort them). Mapping then estimates focal length and lens distortion in COLMAP (a RADIAL
camera by default, principal point kept). Right after mapping, before densification and the
final adjustment, :class:`Undistortion` makes everything pinhole: every keypoint is moved to its
undistorted position (same focal length and principal point), the shared camera becomes
PINHOLE, and the preprocessed ``color/``, ``enhanced/`` frames and ``mask.png`` are undistorted
with the estimate (with :mod:`cystomap.preprocess`'s maps) into a directory of the same layout.
The stage writes it as ``sfm/undistorted/`` (with its pinhole ``camera.json``), and the
estimated camera of the recorded frames as ``sfm/camera.json``. The later stages read frames
through :func:`frames_dir`, so they see undistorted frames that fit the pinhole model.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cystomap.camera import Camera
from cystomap.errors import StageError
from cystomap.images import PNG_WRITE
from cystomap.outputs import write_json
from cystomap.video import ordered_map

log = logging.getLogger(__name__)

#: The sfm output's subdirectory of undistorted frames (present only after self-calibration).
UNDISTORTED = "undistorted"
DISTORTION_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")


def frames_dir(sfm_dir: str | Path, preprocessed_dir: str | Path) -> Path:
    """The directory (``color/``, ``enhanced/``, ``mask.png``) whose frames fit the model in
    ``sfm_dir``: its undistorted frames after self-calibration, else ``preprocessed_dir``."""
    undistorted = Path(sfm_dir) / UNDISTORTED
    if (undistorted / "camera.json").is_file():
        return undistorted
    return Path(preprocessed_dir)


def model_camera(rec: Any, name: str = "camera", calibrated: bool = True) -> Camera:
    """The shared camera of a COLMAP model as a :class:`Camera`."""
    cam = rec.cameras[min(rec.cameras)]
    return Camera.from_colmap(cam.model_name, cam.width, cam.height, cam.params, name=name,
                              calibrated=calibrated)


def _monotonic_radius(camera: Camera) -> bool:
    """Whether the radial distortion keeps the image radius increasing out to the corners
    (otherwise it folds the image and is no usable lens model)."""
    k1, k2 = camera.dist[0], camera.dist[1]
    corner = max(math.hypot(x / camera.fx, y / camera.fy)
                 for x in (camera.cx + 0.5, camera.width - 0.5 - camera.cx)
                 for y in (camera.cy + 0.5, camera.height - 0.5 - camera.cy))
    r = np.linspace(0.0, 1.5 * corner, 200)  # undistorted radii well beyond the corner's
    rd = r * (1 + k1 * r**2 + k2 * r**4)
    reach = np.nonzero(rd >= corner)[0]
    end = int(reach[0]) + 1 if len(reach) else len(r)
    return bool(np.all(np.diff(rd[:end]) > 0)) and bool(len(reach))


class Undistortion:
    """Turns a self-calibrated model pinhole and writes the frames undistorted to fit it.

    ``pre`` is the preprocessed directory, ``out`` the directory that receives ``color/``,
    ``enhanced/``, ``clipped/`` (if ``pre`` has it), ``mask.png`` and ``camera.json``
    (pinhole); ``prior`` the camera the stage started from (its field-of-view guess)."""

    def __init__(self, pre: Path, out: Path, prior: Camera, names: list[str],
                 threads: int) -> None:
        self.pre, self.out, self.prior, self.names, self.threads = pre, out, prior, names, threads
        self.estimated: Camera | None = None
        self.summary: dict[str, Any] = {}

    @property
    def enhanced_dir(self) -> Path:
        return self.out / "enhanced"

    @property
    def color_dir(self) -> Path:
        return self.out / "color"

    @property
    def mask_path(self) -> Path:
        return self.out / "mask.png"

    def __call__(self, rec: Any) -> tuple[Path, Path | None]:
        """Undistort ``rec`` (in place) and the frames; returns (enhanced dir, mask path)."""
        cam = rec.cameras[min(rec.cameras)]
        model = cam.model_name
        rec.update_point_3d_errors()
        error = float(rec.compute_mean_reprojection_error())
        est = model_camera(rec, name=f"{self.prior.name}_estimated", calibrated=False)
        self.estimated = est
        f_prior = 0.5 * (self.prior.fx + self.prior.fy)
        f_est = 0.5 * (est.fx + est.fy)
        ok = _monotonic_radius(est)
        self.summary = {
            "estimated": True, "model": model,
            "params": {n: round(float(v), 6) for n, v in zip(
                cam.params_info.replace(" ", "").split(","), cam.params, strict=True)},
            "prior_focal_px": round(f_prior, 3), "focal_px": round(f_est, 3),
            "focal_vs_prior": round(f_est / f_prior, 4),
            "prior_diagonal_fov_deg": round(self.prior.diagonal_fov_deg, 3),
            "diagonal_fov_deg": round(est.diagonal_fov_deg, 3),
            "k1": round(est.dist[0], 5), "k2": round(est.dist[1], 5),
            "reprojection_error_px": round(error, 4),
            "monotonic": ok,
        }
        log.info("self-calibration (%s): focal %.1f px (prior %.1f, x%.3f), k1 %.4f, k2 %.4f, "
                 "reprojection error %.3f px", model, f_est, f_prior, f_est / f_prior,
                 est.dist[0], est.dist[1], error)
        if not ok:
            raise StageError(
                f"sfm: the self-calibrated lens distortion (k1 {est.dist[0]:.3f}, k2 "
                f"{est.dist[1]:.3f}) folds the image before its corners: no usable calibration; "
                "give the camera's calibration or try self_calibration_model SIMPLE_RADIAL"
            )
        self._undistort_model(rec, est)
        self._undistort_frames(est)
        return self.enhanced_dir, self.mask_path

    @staticmethod
    def _undistort_model(rec: Any, est: Camera) -> None:
        """Keypoints moved to their undistorted positions; the camera made PINHOLE (same K)."""
        import pycolmap

        pinhole = est.without_distortion()
        fx, fy, cx, cy = pinhole.colmap_params("PINHOLE")
        for camera_id in list(rec.cameras):
            cam = rec.camera(camera_id)
            for image_id in rec.reg_image_ids():
                image = rec.image(image_id)
                if image.camera_id != camera_id or image.num_points2D() == 0:
                    continue
                pts = image.points2D
                xy = np.array([p.xy for p in pts], dtype=np.float64)
                n = cam.cam_from_img(xy)
                new = np.column_stack([fx * n[:, 0] + cx, fy * n[:, 1] + cy])
                for p, q in zip(pts, new, strict=True):
                    p.xy = q
            cam.model = pycolmap.CameraModelId.PINHOLE
            cam.params = [fx, fy, cx, cy]
        rec.update_point_3d_errors()

    def _undistort_frames(self, est: Camera) -> None:
        from cystomap.preprocess import PreprocessConfig
        from cystomap.undistortion import _Geometry

        geo = _Geometry(est, PreprocessConfig())  # same K, no resize: the model's pinhole
        for sub in ("color", "enhanced"):
            (self.out / sub).mkdir(parents=True, exist_ok=True)
        mask = cv2.imread(str(self.pre / "mask.png"), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            mask = np.full((est.height, est.width), 255, np.uint8)
        warped = geo.remap(mask, cv2.INTER_LINEAR)
        new_mask = np.where((warped >= 255) & (geo.valid > 0), 255, 0).astype(np.uint8)
        outside = new_mask == 0

        subs = [("color", cv2.IMREAD_COLOR), ("enhanced", cv2.IMREAD_GRAYSCALE)]
        if (self.pre / "clipped").is_dir():  # the preprocess stage's clipped-pixel masks
            (self.out / "clipped").mkdir(parents=True, exist_ok=True)
            subs.append(("clipped", cv2.IMREAD_GRAYSCALE))

        def work(name: str) -> None:
            for sub, flags in subs:
                src = self.pre / sub / name
                img = cv2.imread(str(src), flags)
                if img is None:
                    if sub != "enhanced":
                        continue
                    raise StageError(f"{src}: cannot read image")
                img = geo.remap(img, cv2.INTER_NEAREST if sub == "clipped" else cv2.INTER_LINEAR)
                img[outside] = 0
                if not cv2.imwrite(str(self.out / sub / name), img, PNG_WRITE):
                    raise StageError(f"{self.out / sub / name}: cannot write PNG")

        for _ in ordered_map(work, self.names, self.threads):
            pass
        cv2.imwrite(str(self.mask_path), new_mask)
        geo.out_camera.save(self.out / "camera.json")
        share = float(np.count_nonzero(new_mask)) / new_mask.size
        self.summary["undistorted_mask_share"] = round(share, 4)
        log.info("undistorted %d frames with the estimated camera into %s (mask %.0f%%)",
                 len(self.names), self.out, 100 * share)

    def write(self, out_dir: Path) -> None:
        """The estimated camera of the recorded frames as ``out_dir/camera.json``."""
        if self.estimated is None:
            return
        cam = self.estimated
        write_json(out_dir / "camera.json", {**cam.to_dict(), "source": "self-calibration",
                                             "fit": self.summary})


def fixed_summary(camera: Camera) -> dict[str, Any]:
    """quality.json's calibration entry when the intrinsics were not estimated."""
    return {"estimated": False, "calibrated": camera.calibrated,
            "focal_px": round(0.5 * (camera.fx + camera.fy), 3),
            "diagonal_fov_deg": round(camera.diagonal_fov_deg, 3)}

