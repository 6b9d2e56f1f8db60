"""Stage ``preprocess``: undistort the kept frames, mask the field of view, level and enhance.

For every frame (as in the paper: "All camera frames were undistorted ... brightness was leveled
using a Gaussian-smoothed mask, and contrast was enhanced"):

1. optional resize by ``scale`` (INTER_AREA when shrinking; intrinsics scaled, distortion
   coefficients unchanged since they act on normalised coordinates), then undistortion with one
   ``cv2.initUndistortRectifyMap`` computed once and ``cv2.remap`` per frame. The new pinhole
   camera (``new_camera``) is by default the same K: nothing outside the source image is
   invented, and any output pixel whose source lies outside the frame is masked out;
2. field-of-view mask (``mask``): detected from a high temporal percentile of sampled frames
   (the lit circle/octagon of endoscope video, minus static overlays; see
   :mod:`cystomap.video`), the whole frame, or a circle; always intersected with the
   undistortion's valid area and eroded a few pixels;
3. brightness levelling: the luminance is divided by its Gaussian-smoothed version (sigma a
   fraction of the image diagonal) computed only inside the mask by normalised convolution
   (first order, i.e. a Gaussian-weighted local linear fit, so neither the FOV rim nor the image
   edges are biased); the gain is rescaled to keep the frame's mean level (or ``level_mean``)
   and applied equally to B, G and R, so colour ratios are kept;
4. contrast enhancement for matching: CLAHE on the levelled luminance.

Outputs in ``out_dir`` (written atomically): ``color/<name>.png`` (undistorted + levelled BGR, for
the atlas), ``enhanced/<name>.png`` (grey, levelled + CLAHE, for feature matching), with the same
file names as the input frames and 0 outside the mask; ``mask.png`` (uint8, 255 = valid);
``camera.json`` (the undistorted pinhole camera, distortion all zero, at the output size);
``masks/<name>.png`` (uint8 per frame, 255 = valid: ``mask.png`` minus the frame's specular
glints and their rims, see :func:`glint_mask`; COLMAP's per-image mask convention; when
``glint_z`` > 0); ``clipped/<name>.png`` (uint8 per frame, 255 = a colour channel of the
undistorted frame clipped, see :func:`clipped_mask`; the atlas gives those pixels no weight;
when ``clip_level`` > 0); ``preprocess.json`` (settings, frames processed, mask area share,
glint and clipped shares, timing).
"""

from __future__ import annotations

import logging
import math
import struct
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cystomap.camera import Camera
from cystomap.errors import InputError, StageError
from cystomap.glints import clipped_mask, glint_mask
from cystomap.images import PNG_WRITE
from cystomap.outputs import atomic_dir, software_versions, write_json
from cystomap.settings import setting, validate
from cystomap.undistortion import _Geometry
from cystomap.video import (
    circle_mask,
    erode,
    fit_circle,
    fov_mask,
    lit_extent,
    ordered_map,
    static_pixels,
    temporal_std,
)

log = logging.getLogger(__name__)

PROGRESS_EVERY_S = 5.0
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_MASK_WORK_WIDTH = 480  # FOV detection runs at most at this width
# levelling: cells this many robust standard deviations darker than the fit are lumen, and
# at least this much darker (log ratio: under half the fitted light). Without the floor the
# test is a tail cut: on phantom frames with no lumen in view the darkest 1-2 % of cells lie
# 4 robust sd (about 0.13) below the median, from ordinary shading (2026-12-05)
DARK_Z = 4.0
DARK_MIN_LOG = math.log(2.0)


@dataclass(frozen=True)
class PreprocessConfig:
    """Settings of the ``preprocess`` stage (config section ``preprocess``)."""

    # Resize factor of the outputs (and of camera.json) relative to the input frames,
    # e.g. 0.375 turns 1280x720 into 480x270; max_image_size may lower it further. Every
    # later stage works at this size: 0.5 for 1080p recordings cut preprocess by 70 % and the
    # atlas by 64 % on a 60 s phantom recording with the same frames registered and an atlas
    # as close to the truth (docs/measurements.md, "1080p at half the working size").
    scale: float = setting(1.0, "(0, 4]")
    # Largest working size: the outputs are shrunk further (INTER_AREA) so that the longest
    # side of the lit field of view (the detected mask's bounding box; the frame's with mask
    # "full") is at most this many pixels; 0 = no limit. preprocess.json records the scale
    # used. 1280 is twice the size SfM detects its features at (sfm.max_image_size 640) and
    # the size of its second mapping: 1280x720 and smaller video and a scope's round image
    # in a 1080p frame keep their size, a 1080p frame filled by the image works at 1280x720
    # (960 there: the model of scale 0.5 digit for digit, 4-9 s sooner on a 60 s recording;
    # docs/measurements.md, "The working size bounded by the lit field"). Not applied with mask "circle" and an
    # explicit mask_radius (given in output pixels).
    max_image_size: int = setting(1280, ">= 0")
    # Pinhole camera of the undistorted images (principal point and aspect ratio always kept,
    # only the focal length changes): "same" = keep fx, fy, cx, cy (with barrel distortion the
    # far periphery of the source falls outside); "crop" = the focal length at which every output
    # pixel has a source pixel (like getOptimalNewCameraMatrix alpha=0); "full" = every source
    # pixel lands in the output (alpha=1; the unfilled corners are masked out). Invalid output
    # pixels are always masked, so no black border is taken for mucosa.
    new_camera: str = setting("same", choices=("same", "crop", "full"))
    # Field-of-view mask: "auto" = detect the lit area from the frames, "full" = whole frame,
    # "circle" = a circle (mask_radius/mask_center, or fitted to the detected FOV rim).
    mask: str = setting("auto", choices=("auto", "full", "circle"))
    # Circle mode: radius in output pixels; 0 = fit the circle to the detected FOV rim.
    mask_radius: float = setting(0.0, ">= 0")
    # Circle mode with a radius: centre (x, y) in output pixels; None = the image centre.
    mask_center: tuple[float, float] | None = None
    # Erode the mask by this many output pixels (soft FOV rim, interpolation at its edge).
    mask_erode_px: int = setting(3, ">= 0")
    # Frames sampled evenly to detect the FOV ("auto" and fitted "circle").
    mask_samples: int = setting(50, ">= 1")
    # "auto" mode: FOV pixels whose temporal std over the samples is below mask_static_rel
    # times the typical one (overlaid text, logos, lens dirt) are masked out, so matching does
    # not pair static features; needs 8+ frames, skipped if over 10% of the FOV is static
    # (0 = off).
    mask_static_rel: float = setting(0.25, "[0, 1)")
    # Sigma of the Gaussian illumination estimate, as a fraction of the image diagonal
    # (0 = no brightness levelling).
    level_sigma: float = setting(0.08, "[0, 1]")
    # The levelling gain is clipped to [1 / level_max_gain, level_max_gain] (dark lumen areas
    # are not amplified into noise).
    level_max_gain: float = setting(4.0, ">= 1")
    # Leave areas far darker than the fitted illumination (the lumen: the bladder neck's
    # opening, the dark end of a tube: under half the fitted light and more than 4 robust
    # standard deviations below the frame's median ratio) out of the illumination fit of the
    # colour frames (for the atlas), so the wall around them is not brightened. The enhanced
    # frames (for matching) keep the plain fit: CLAHE follows them anyway, and changing them
    # moved the SfM of the entry frames on a glint test session (flagged, 7.4 mm off).
    # Off by default: on dev FROC pairs 300, 301, 306, 308 and no-change 1300 (same frames,
    # SfM and mesh; colour frames and atlases rebuilt) change detection found 18/24 lesions
    # with it and 23/24 without, 0 false regions either way (docs/measurements.md, "The lumen refit off").
    level_exclude_dark: bool = False
    # Mean luminance (0-255) inside the mask after levelling: 0 = each frame keeps its own.
    level_mean: float = setting(0.0, "[0, 255]")
    # CLAHE clip limit for the enhanced images (0 = no CLAHE, levelled grey only).
    clahe_clip: float = setting(2.0, ">= 0")
    # CLAHE tiles along the longer image side (square tiles).
    clahe_tiles: int = setting(8, ">= 1")
    # Worker threads (PNG decoding/encoding and OpenCV release the GIL).
    threads: int = setting(2, ">= 1")
    # Specular glints (masks/<name>.png per frame, 0 = glint or outside the FOV): a pixel is a
    # glint core when its whiteness (smallest of B, G, R of the levelled frame) lies more than
    # glint_z robust standard deviations (1.4826 MAD) above the frame's median and it is less
    # coloured than the frame's median pixel; the blob grows into connected pixels above half
    # that (its rim) and is dilated by glint_dilate times the image diagonal. 0 = no masks.
    glint_z: float = setting(6.0, ">= 0")
    glint_dilate: float = setting(0.006, "[0, 0.1]")
    # Clipped pixels (clipped/<name>.png per frame, 255 = clipped): any of B, G, R of the
    # undistorted frame (before levelling) at or above this 8-bit level, dilated by
    # glint_dilate. A clipped channel is not the wall's colour (overexposed reddish mucosa
    # turns pale), so the atlas does not blend them. 0 = no clipped masks.
    clip_level: int = setting(250, "[0, 255]")

    def __post_init__(self) -> None:
        validate(self, "preprocess", {
            "mask_center [x, y] or null": self.mask_center is None or len(self.mask_center) == 2,
        })

def preprocess_frames(
    frames_dir: str | Path, out_dir: str | Path, camera: Camera,
    cfg: PreprocessConfig | None = None,
) -> Path:
    """Undistort, mask, level and enhance every ``*.png`` of ``frames_dir`` into ``out_dir``.

    Raises :class:`InputError` if ``frames_dir`` has no PNG, or a frame is unreadable or not of
    the camera's size (the message names the file). Nothing is left at ``out_dir`` on failure.
    """
    cfg = cfg or PreprocessConfig()
    frames_dir, out_dir = Path(frames_dir), Path(out_dir)
    t0 = time.perf_counter()
    paths = _list_frames(frames_dir, camera)
    geo = _Geometry(camera, cfg)
    fov = _lit_field(paths, geo, cfg)
    scale = working_scale(fov, cfg, (geo.width, geo.height))
    if scale != cfg.scale:
        geo = _Geometry(camera, cfg, scale)
        log.info("preprocess: working at scale %.4g (%dx%d; scale %g asked): the lit field's "
                 "longest side at most max_image_size %d px", scale, geo.width, geo.height,
                 cfg.scale, cfg.max_image_size)
        if fov is not None:
            fov = _resized_mask(fov, geo.width, geo.height)
    mask, circle = _field_of_view(fov, geo, cfg)
    share = float(np.count_nonzero(mask)) / mask.size
    if share < 0.01:
        raise StageError(f"{frames_dir}: the field-of-view mask is empty (mask={cfg.mask!r})")
    log.info("preprocess: %d frames, %dx%d -> %dx%d, mask %s covers %.0f%% (%.1f s)", len(paths),
             camera.width, camera.height, geo.width, geo.height, cfg.mask, 100 * share,
             time.perf_counter() - t0)
    leveller = _Leveller(mask, cfg)
    with atomic_dir(out_dir) as tmp:
        (tmp / "color").mkdir()
        (tmp / "enhanced").mkdir()
        if cfg.glint_z > 0:
            (tmp / "masks").mkdir()
        if cfg.clip_level > 0:
            (tmp / "clipped").mkdir()

        def work(path: Path) -> tuple[float, float, float]:
            return _process(path, tmp, geo, mask, leveller, cfg)

        last_log = time.perf_counter()
        levels, glints, clips = [], [], []
        for level, glint, clip in ordered_map(work, paths, cfg.threads):
            levels.append(level)
            glints.append(glint)
            clips.append(clip)
            now = time.perf_counter()
            if now - last_log > PROGRESS_EVERY_S:
                last_log = now
                log.info("preprocess: %d/%d frames, %.1f s", len(levels), len(paths), now - t0)
        cv2.imwrite(str(tmp / "mask.png"), mask)
        geo.out_camera.save(tmp / "camera.json")
        summary: dict[str, Any] = {
            "frames_dir": str(frames_dir),
            "frames": len(paths),
            "input_camera": camera.to_dict(),
            "camera": geo.out_camera.to_dict(),
            "scale": geo.scale,
            "mask": {"mode": cfg.mask, "area_share": round(share, 4),
                     "circle": [round(v, 2) for v in circle] if circle else None},
            "mean_level": {"min": round(min(levels), 2), "max": round(max(levels), 2)},
            "glint_share": {"mean": round(float(np.mean(glints)), 5),
                            "max": round(float(np.max(glints)), 5),
                            "frames_with_glints": int(np.count_nonzero(glints))}
            if cfg.glint_z > 0 else None,
            "clipped_share": {"mean": round(float(np.mean(clips)), 5),
                              "max": round(float(np.max(clips)), 5),
                              "frames_with_clipping": int(np.count_nonzero(clips))}
            if cfg.clip_level > 0 else None,
            "settings": asdict(cfg),
            "elapsed_s": round(time.perf_counter() - t0, 3),
        }
        write_json(tmp / "preprocess.json", {**summary, "software": software_versions()})
    log.info("preprocess: wrote %d frames to %s in %.1f s", len(paths), out_dir,
             time.perf_counter() - t0)
    return out_dir


# --------------------------------------------------------------------------- inputs


def _list_frames(frames_dir: Path, camera: Camera) -> list[Path]:
    """The PNG frames, sorted; header checks (PNG, size) before any heavy work."""
    if not frames_dir.is_dir():
        raise InputError(f"{frames_dir}: frames directory not found")
    paths = sorted(p for p in frames_dir.glob("*.png") if p.is_file())
    if not paths:
        raise InputError(f"{frames_dir}: no PNG frames in the directory")
    for path in paths:
        try:
            with path.open("rb") as fh:
                head = fh.read(24)
        except OSError as exc:
            raise InputError(f"{path}: cannot read ({exc})") from exc
        if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
            raise InputError(f"{path}: not a readable PNG image")
        width, height = struct.unpack(">II", head[16:24])
        _check_size(path, width, height, camera)
    return paths


def _check_size(path: Path, width: int, height: int, camera: Camera) -> None:
    if (width, height) != (camera.width, camera.height):
        raise InputError(f"{path}: frame size {width}x{height} does not match camera "
                         f"{camera.name!r} ({camera.width}x{camera.height})")


def _read(path: Path, camera: Camera, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
    image = cv2.imread(str(path), flags)
    if image is None:
        raise InputError(f"{path}: cannot decode PNG (corrupt or truncated)")
    _check_size(path, image.shape[1], image.shape[0], camera)
    return image


def _explicit_circle(cfg: PreprocessConfig) -> bool:
    return cfg.mask == "circle" and cfg.mask_radius > 0


def _lit_field(paths: list[Path], geo: _Geometry, cfg: PreprocessConfig) -> np.ndarray | None:
    """The detected field of view at ``geo``'s size (255 = lit), or None where it is not
    detected (mask "full", or "circle" with an explicit radius)."""
    if cfg.mask == "full" or _explicit_circle(cfg):
        return None
    return _detect_fov(paths, geo, cfg, with_static=cfg.mask == "auto")


def working_scale(fov: np.ndarray | None, cfg: PreprocessConfig, size: tuple[int, int]) -> float:
    """``cfg.scale``, lowered so the lit field's longest side (``fov`` at ``cfg.scale``; the
    image's, ``size`` at ``cfg.scale``, without one) is at most ``cfg.max_image_size``."""
    if cfg.max_image_size <= 0 or _explicit_circle(cfg):
        return cfg.scale
    longest = lit_extent(fov) if fov is not None else max(size)
    if longest <= cfg.max_image_size:
        return cfg.scale
    return cfg.scale * cfg.max_image_size / longest


def _resized_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """A 0/255 mask at another size (linear, then thresholded at half)."""
    if mask.shape == (height, width):
        return mask
    resized = cv2.resize(mask, (width, height), interpolation=cv2.INTER_LINEAR)
    return np.where(resized >= 128, 255, 0).astype(np.uint8)


def _field_of_view(
    detected: np.ndarray | None, geo: _Geometry, cfg: PreprocessConfig
) -> tuple[np.ndarray, tuple[float, float, float] | None]:
    """Final mask (output size, 255 = valid) from the ``detected`` field of view (output size;
    :func:`_lit_field`), and the circle used, if any."""
    h, w = geo.height, geo.width
    circle: tuple[float, float, float] | None = None
    if cfg.mask == "full":
        fov = np.full((h, w), 255, np.uint8)
    elif _explicit_circle(cfg):
        cx, cy = cfg.mask_center if cfg.mask_center is not None else ((w - 1) / 2, (h - 1) / 2)
        circle = (float(cx), float(cy), float(cfg.mask_radius))
        fov = circle_mask((h, w), *circle)
    else:
        assert detected is not None
        fov = detected
        if cfg.mask == "circle":
            circle = fit_circle(fov)
            if circle is None:
                log.warning("preprocess: no FOV rim to fit a circle to; using the detected mask")
            else:
                fov = circle_mask((h, w), *circle)
    mask = cv2.bitwise_and(fov, geo.valid)
    return erode(mask, cfg.mask_erode_px), circle


def _detect_fov(paths: list[Path], geo: _Geometry, cfg: PreprocessConfig, with_static: bool
                ) -> np.ndarray:
    h, w = geo.height, geo.width
    f = min(1.0, _MASK_WORK_WIDTH / w)
    work = (max(8, round(w * f)), max(8, round(h * f)))
    picks = np.unique(np.round(np.linspace(0, len(paths) - 1,
                                           min(cfg.mask_samples, len(paths)))).astype(int))

    def sample(path: Path) -> np.ndarray:
        grey = geo.undistort(_read(path, geo.camera, cv2.IMREAD_GRAYSCALE))
        return cv2.resize(grey, work, interpolation=cv2.INTER_AREA)

    stack = np.stack(list(ordered_map(sample, [paths[i] for i in picks], cfg.threads)))
    level = np.percentile(stack, 75, axis=0) if len(stack) > 1 else stack[0]
    variation = temporal_std(stack) if len(stack) >= 8 else None
    mask = fov_mask(level, variation)
    if mask is None:
        log.warning("preprocess: no field of view found (dark frames?); using the whole frame")
        mask = np.full(stack.shape[1:], 255, np.uint8)
    if with_static:
        # away from the rim: the hull's outermost pixels are black in every frame
        static = static_pixels(variation, erode(mask, 4) > 0, cfg.mask_static_rel)
        if static is not None:
            log.info("preprocess: %.1f%% of the FOV is static (overlay, lens dirt): masked out",
                     100 * np.count_nonzero(static) / np.count_nonzero(mask))
            mask[static] = 0
    return _resized_mask(mask, w, h)


# --------------------------------------------------------------------------- photometry


class _Leveller:
    """Brightness levelling: luminance divided by its smoothed version inside the mask.

    The illumination is a Gaussian-weighted local *linear* fit of the luminance over the mask
    pixels (first-order normalised convolution, Knutsson & Westin): inside the FOV it equals the
    usual normalised Gaussian smoothing G(L·m)/G(m), but at the FOV rim and the image edges,
    where the window is one-sided, it follows the falloff instead of flattening it (a plain
    normalised convolution would leave the rim too dark or too bright under strong vignetting).
    It runs on a copy downscaled so the Gaussian is ~4 px wide: same result for a smooth
    illumination, a fraction of the cost of a huge kernel at full size.
    """

    def __init__(self, mask: np.ndarray, cfg: PreprocessConfig) -> None:
        self.cfg = cfg
        self.inside = mask > 0
        h, w = mask.shape
        self.size = (w, h)
        sigma = cfg.level_sigma * math.hypot(w, h)
        self.enabled = sigma > 0 and bool(self.inside.any())
        if not self.enabled:
            return
        f = min(1.0, 4.0 / sigma)
        self.small = (max(4, round(w * f)), max(4, round(h * f)))
        self.sigma_small = sigma * self.small[0] / w
        m = cv2.resize(self.inside.astype(np.float64), self.small, interpolation=cv2.INTER_AREA)
        self.m = m
        sh, sw = m.shape
        yy, xx = np.mgrid[0:sh, 0:sw].astype(np.float64)
        self.x, self.y = xx - (sw - 1) / 2, yy - (sh - 1) / 2
        self.row = self._fit_rows(m)

    def _fit_rows(self, m: np.ndarray) -> np.ndarray:
        """Per small pixel, the first row of the inverse moment matrix of the local linear fit
        over the support ``m`` (the weights that give the fitted value at the pixel)."""
        x, y, blur = self.x, self.y, self._blur
        s0 = blur(m)
        sx, sy = blur(m * x) - x * s0, blur(m * y) - y * s0
        sxx = blur(m * x * x) - 2 * x * blur(m * x) + x * x * s0
        syy = blur(m * y * y) - 2 * y * blur(m * y) + y * y * s0
        sxy = blur(m * x * y) - x * blur(m * y) - y * blur(m * x) + x * y * s0
        a = np.stack([np.stack([s0, sx, sy], -1), np.stack([sx, sxx, sxy], -1),
                      np.stack([sy, sxy, syy], -1)], -2)
        det = np.linalg.det(a)
        scale = np.maximum(s0 * sxx * syy, 1e-300)
        ok = (s0 > 1e-3 * s0.max()) & (det > 1e-4 * scale)
        row = np.zeros(a.shape[:-1])
        row[ok] = np.linalg.inv(a[ok])[:, 0, :]  # first row: the fitted value at the pixel
        row[~ok, 0] = 1.0 / np.maximum(s0[~ok], 1e-12)  # too little support: plain average
        return row

    def _blur(self, image: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(image, (0, 0), self.sigma_small, borderType=cv2.BORDER_CONSTANT)

    def _fit(self, ml: np.ndarray, m: np.ndarray, row: np.ndarray) -> np.ndarray:
        """The local linear fit of the small luminance sum ``ml`` over the support ``m``."""
        sl = self._blur(ml)
        slx = self._blur(ml * self.x) - self.x * sl
        sly = self._blur(ml * self.y) - self.y * sl
        fitted = row[..., 0] * sl + row[..., 1] * slx + row[..., 2] * sly
        # never below a fraction of the plain local average (guards an extrapolated fit)
        plain = sl / np.maximum(self._blur(m), 1e-12)
        return np.maximum(fitted, 0.25 * plain)

    def dark_cells(self, ml: np.ndarray, fitted: np.ndarray) -> np.ndarray:
        """Small-image cells far darker than the fitted illumination: the lumen (the neck's
        opening, the dark end of a tube). Their log ratio to the fit lies more than DARK_Z
        robust standard deviations (1.4826 MAD over the cells) and at least DARK_MIN_LOG below
        the cells' median, and the cells next to them (the lumen's edge crosses them); the
        cells average a few hundred pixels, so thin dark texture (vessels) does not reach it."""
        full = self.m > 0.5
        if full.sum() < 16:
            return np.zeros_like(full)
        mean = ml / np.maximum(self.m, 1e-12)
        r = np.log((mean + 1.0) / (np.maximum(fitted, 0.0) + 1.0))
        med = float(np.median(r[full]))
        spread = 1.4826 * float(np.median(np.abs(r[full] - med)))
        dark = full & (r < med - max(DARK_Z * spread, DARK_MIN_LOG))
        # and the cells around it, which the lumen's edge crosses (part lumen, part wall)
        return full & (cv2.dilate(dark.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)

    def illumination(self, lum: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The plain fit and, with ``level_exclude_dark`` and a lumen in view, the fit without
        the lumen (else None), both at full size."""
        # area-average L·m (not L): border pixels outside the mask must not leak in
        ml = cv2.resize(np.where(self.inside, lum, 0).astype(np.float64), self.small,
                        interpolation=cv2.INTER_AREA)
        fitted = self._fit(ml, self.m, self.row)
        refit = None
        if self.cfg.level_exclude_dark:
            # a dark lumen in the window would pull the fit down and brighten the wall around
            # it (a halo that differs from frame to frame): fit again without it
            dark = self.dark_cells(ml, fitted)
            if dark.any():
                m = np.where(dark, 0.0, self.m)
                refit = self._fit(np.where(dark, 0.0, ml), m, self._fit_rows(m))
        return (self._full(fitted), None if refit is None else self._full(refit))

    def _full(self, small: np.ndarray) -> np.ndarray:
        return cv2.resize(small.astype(np.float32), self.size, interpolation=cv2.INTER_LINEAR)

    def gain(self, lum: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None, float]:
        """Per-pixel gains for the enhanced and for the colour frames (None = no levelling;
        the same array unless a lumen is left out of the colour's fit) and the target mean
        luminance."""
        inside = self.inside if self.inside.any() else np.ones(lum.shape, bool)
        mean = float(lum[inside].mean())
        target = self.cfg.level_mean or mean
        if not self.enabled:
            if self.cfg.level_mean > 0 and mean > 0:
                flat = np.full(lum.shape, target / mean, np.float32)
                return flat, flat, target
            return None, None, mean
        plain, refit = self.illumination(lum)
        g = self._gain(lum, plain, inside, target)
        return g, (g if refit is None else self._gain(lum, refit, inside, target)), target

    def _gain(self, lum: np.ndarray, illumination: np.ndarray, inside: np.ndarray,
              target: float) -> np.ndarray:
        inv = 1.0 / np.maximum(illumination, 1.0)
        levelled_mean = float((lum * inv)[inside].mean())
        g = inv * (target / max(levelled_mean, 1e-6))
        mg = self.cfg.level_max_gain
        return np.clip(g, 1.0 / mg, mg).astype(np.float32)


def _process(
    path: Path, out: Path, geo: _Geometry, mask: np.ndarray, leveller: _Leveller,
    cfg: PreprocessConfig,
) -> tuple[float, float, float]:
    """Write color/, enhanced/ (and masks/, clipped/) for one frame; returns its mean luminance
    inside the mask and the shares of the mask taken by glints and by clipped pixels."""
    image = geo.undistort(_read(path, geo.camera))
    lum = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float32)
    gain, color_gain, target = leveller.gain(lum)
    outside = mask == 0

    def levelled(g: np.ndarray | None) -> np.ndarray:
        out = image.copy() if g is None else np.clip(image.astype(np.float32) * g[..., None],
                                                     0, 255).astype(np.uint8)
        out[outside] = 0
        return out

    matched = levelled(gain)
    color = matched if color_gain is gain else levelled(color_gain)
    grey = cv2.cvtColor(matched, cv2.COLOR_BGR2GRAY)
    level = float(grey[~outside].mean()) if (~outside).any() else 0.0
    if cfg.clahe_clip > 0:
        # fill the outside with the mean level so the border does not skew CLAHE's histograms
        grey[outside] = min(255, round(target))
        h, w = grey.shape
        tile = max(h, w) / cfg.clahe_tiles
        grid = (max(1, round(w / tile)), max(1, round(h / tile)))
        grey = cv2.createCLAHE(clipLimit=cfg.clahe_clip, tileGridSize=grid).apply(grey)
        grey[outside] = 0
    outputs = [("color", color), ("enhanced", grey)]
    share = clip_share = 0.0
    inside = max(1, int(np.count_nonzero(mask)))
    if cfg.glint_z > 0:
        glint = glint_mask(matched, mask, cfg.glint_z, cfg.glint_dilate)
        share = float(np.count_nonzero(glint & (mask > 0))) / inside
        outputs.append(("masks", np.where(glint, 0, mask).astype(np.uint8)))
    if cfg.clip_level > 0:
        clipped = clipped_mask(image, mask, cfg.clip_level, cfg.glint_dilate)
        clip_share = float(np.count_nonzero(clipped)) / inside
        outputs.append(("clipped", np.where(clipped, 255, 0).astype(np.uint8)))
    for sub, img in outputs:
        target_path = out / sub / path.name
        if not cv2.imwrite(str(target_path), img, PNG_WRITE):
            raise StageError(f"{target_path}: cannot write PNG")
    return level, share, clip_share
