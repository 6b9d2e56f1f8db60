"""SIFT features of the enhanced frames, inside the field-of-view mask, into a COLMAP database.

The frames are resized with OpenCV (area filter) before COLMAP's SIFT runs on them, which is
several times faster than letting COLMAP read and resize the full frames; keypoints and the
camera are scaled back afterwards, so the database is in pixels of the full-size frames.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cystomap.camera import Camera, colmap_params
from cystomap.errors import InputError
from cystomap.sfm.config import SfmConfig
from cystomap.video import lit_extent as video_lit_extent

log = logging.getLogger(__name__)

FRAME_RE = re.compile(r"(\d+)\.png$", re.IGNORECASE)


@dataclass(frozen=True)
class Features:
    """What the feature step put into the database."""

    names: list[str]  # image names in video order (= database order)
    num_keypoints: dict[str, int]
    scale: float  # working size / full size
    # frames detected again on the image doubled (too plain at the working size, see
    # SfmConfig.plain_keypoints_share), in video order
    plain: tuple[str, ...] = ()


def list_frames(enhanced_dir: Path) -> list[str]:
    """PNG frame names in video order (by the frame index in their name)."""
    if not enhanced_dir.is_dir():
        raise InputError(f"{enhanced_dir}: no such directory (expected the preprocessed frames)")
    found = []
    for p in enhanced_dir.iterdir():
        m = FRAME_RE.search(p.name)
        if m and p.is_file():
            found.append((int(m.group(1)), p.name))
    if not found:
        raise InputError(f"{enhanced_dir}: no frame PNGs (names like f000123.png)")
    found.sort()
    return [name for _, name in found]


def colmap_camera(camera: Camera, model: str = "PINHOLE") -> tuple[float, ...]:
    """Parameters of COLMAP ``model`` (PINHOLE, or a self-calibrated model such as RADIAL) in
    COLMAP's convention (:func:`cystomap.camera.colmap_params`)."""
    return colmap_params(camera, model)


def lit_extent(mask_path: Path | None, camera: Camera) -> int:
    """Longest side (px) of the bounding box of the lit field of view (mask.png > 127); the
    frame's longest side without a mask. A scope whose round image fills half of a black
    frame then gets the working size of one that fills it (issue 12, item 7)."""
    longest = max(camera.width, camera.height)
    if mask_path is None or not mask_path.is_file():
        return longest
    mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
    if mask is None or not (mask > 127).any():
        return longest  # reported by _working_mask
    return video_lit_extent(mask)


def working_scale(camera: Camera, cfg: SfmConfig, lit_px: int | None = None) -> float:
    """Working size / full size: ``max_image_size`` over the longest side of the lit field
    of view (``lit_px``; the frame's without it), at most 1."""
    longest = lit_px or max(camera.width, camera.height)
    if cfg.max_image_size <= 0 or cfg.max_image_size >= longest:
        return 1.0
    return cfg.max_image_size / longest


def extract(
    enhanced_dir: Path,
    mask_path: Path | None,
    camera: Camera,
    names: list[str],
    database: Path,
    work_dir: Path,
    cfg: SfmConfig,
    model: str = "PINHOLE",
    masks_dir: Path | None = None,
) -> Features:
    """Detect SIFT features of ``names`` and write them, one shared camera (COLMAP ``model``:
    PINHOLE, or SIMPLE_PINHOLE when one focal length is to be refined), to ``database``.

    ``masks_dir`` (optional) holds a mask per frame (same name, 0 = no features: specular
    glints, see :func:`cystomap.glints.glint_mask`); it is combined with the field-of-view
    mask and handed to COLMAP as per-image masks."""
    import pycolmap

    lit = lit_extent(mask_path, camera)
    scale = working_scale(camera, cfg, lit)
    if lit < max(camera.width, camera.height):
        log.info("features: the lit field of view is %d px across (frame %dx%d); working "
                 "scale %.3f", lit, camera.width, camera.height, scale)
    small = camera.scaled(scale) if scale != 1.0 else camera
    size = (small.width, small.height)
    image_dir = enhanced_dir
    suffix = ""  # resized copies are uncompressed BMPs (fast); renamed back in the database
    if scale != 1.0:
        image_dir = work_dir / "images"
        image_dir.mkdir(parents=True, exist_ok=True)
        suffix = ".bmp"

        def resize(name: str) -> None:
            img = cv2.imread(str(enhanced_dir / name), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise InputError(f"{enhanced_dir / name}: cannot read image")
            _check_size(img, camera, enhanced_dir / name)
            img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
            cv2.imwrite(str(image_dir / (name + suffix)), img)

        with ThreadPoolExecutor(cfg.num_threads) as pool:
            list(pool.map(resize, names))
    else:
        first = cv2.imread(str(enhanced_dir / names[0]), cv2.IMREAD_GRAYSCALE)
        if first is None:
            raise InputError(f"{enhanced_dir / names[0]}: cannot read image")
        _check_size(first, camera, enhanced_dir / names[0])

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = model
    reader.camera_params = ",".join(f"{v:.10g}" for v in colmap_camera(small, model))
    mask = _working_mask(mask_path, camera, size, scale, cfg)
    if masks_dir is not None:
        frame_masks = work_dir / "masks"
        frame_masks.mkdir(parents=True, exist_ok=True)

        def combine(name: str) -> None:
            m = frame_mask(masks_dir / name, camera, size, mask)
            cv2.imwrite(str(frame_masks / (name + suffix + ".png")), m)  # COLMAP's naming

        with ThreadPoolExecutor(cfg.num_threads) as pool:
            list(pool.map(combine, names))
        reader.mask_path = str(frame_masks)
    elif mask is not None:
        mask_file = work_dir / "mask.png"
        cv2.imwrite(str(mask_file), mask)
        reader.camera_mask_path = str(mask_file)

    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = cfg.num_threads
    opts.max_image_size = max(size)
    sift = opts.sift
    sift.max_num_features = cfg.max_num_features
    sift.first_octave = cfg.first_octave
    sift.num_octaves = cfg.num_octaves
    sift.peak_threshold = cfg.peak_threshold
    sift.edge_threshold = cfg.edge_threshold
    sift.estimate_affine_shape = cfg.estimate_affine_shape
    sift.domain_size_pooling = cfg.domain_size_pooling
    # images enter the database in video order first (single-threaded), so that image ids,
    # and with them everything downstream, do not depend on thread timing
    pycolmap.Database.open(str(database)).close()
    files = [name + suffix for name in names]
    pycolmap.import_images(database, image_dir, pycolmap.CameraMode.SINGLE, files, reader)
    pycolmap.extract_features(
        database, image_dir, image_names=files, camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader, extraction_options=opts, device=pycolmap.Device.cpu,
    )
    plain = _redetect_plain(database, image_dir, files, reader, opts, work_dir, cfg)

    counts: dict[str, int] = {}
    db = pycolmap.Database.open(str(database))
    try:
        cams = db.read_all_cameras()
        if len(cams) != 1:
            raise RuntimeError(f"expected one shared camera in the database, found {len(cams)}")
        cam = cams[0]
        cam.width, cam.height = camera.width, camera.height
        cam.params = list(colmap_camera(camera, model))
        db.update_camera(cam)
        sx, sy = camera.width / small.width, camera.height / small.height
        for image in db.read_all_images():
            if suffix and image.name.endswith(suffix):
                image.name = image.name[: -len(suffix)]
                db.update_image(image)
            kp = np.array(db.read_keypoints(image.image_id), dtype=np.float32)
            if scale != 1.0 and len(kp):
                kp[:, 0] *= sx
                kp[:, 1] *= sy
                if kp.shape[1] >= 6:
                    kp[:, 2:4] *= sx
                    kp[:, 4:6] *= sy
                elif kp.shape[1] >= 3:
                    kp[:, 2] *= 0.5 * (sx + sy)
                db.update_keypoints(image.image_id, kp)
            counts[image.name] = len(kp)
    finally:
        db.close()
    missing = [n for n in names if n not in counts]
    if missing:
        log.warning("%d frame(s) could not be read by COLMAP, e.g. %s", len(missing), missing[0])
    values = np.array(list(counts.values()) or [0])
    log.info("features: %d frames at %dx%d, %d-%d (median %d) keypoints per frame",
             len(counts), size[0], size[1], values.min(), values.max(), int(np.median(values)))
    plain_names = tuple(f[: -len(suffix)] if suffix else f for f in plain)
    return Features(names=names, num_keypoints=counts, scale=scale, plain=plain_names)


def plain_session(counts: list[int], cfg: SfmConfig) -> bool:
    """Whether the frames are too plain at the working size: the median frame has fewer
    keypoints than ``plain_keypoints_share`` of ``max_num_features``. One decision for the
    whole session, not per frame: every frame is matched with others (neighbours and loop
    pairs), and frames detected at different octaves match worse (on two family-B phantom
    sessions, doubling the 60-90 % of frames in plain stretches registered 50 and 59 frames,
    doubling all 120 and 106)."""
    limit = cfg.plain_keypoints_share * cfg.max_num_features
    return bool(limit > 0 and counts and float(np.median(counts)) < limit)


def doubled_frames(features: Features, n_frames: int, cfg: SfmConfig) -> int:
    """How many of the ``n_frames`` frames had their features detected on the image doubled:
    every one when ``first_octave`` is below 0 (the doubled second mapping of
    :func:`cystomap.sfm.retry.finer`), else those of the plain-frame rule."""
    return n_frames if cfg.first_octave < 0 else len(features.plain)


def matching_config(features: Features, cfg: SfmConfig) -> SfmConfig:
    """``cfg`` for matching: with guided matching when the frames were plain (detected again
    doubled) and ``plain_guided_matching`` is on."""
    if features.plain and cfg.plain_guided_matching and not cfg.guided_matching:
        log.info("features: plain frames: guided matching (sfm.plain_guided_matching)")
        return dataclasses.replace(cfg, guided_matching=True)
    return cfg


def _redetect_plain(database: Path, image_dir: Path, files: list[str], reader: object,
                    opts: object, work_dir: Path, cfg: SfmConfig) -> list[str]:
    """Detect every frame again one octave finer (the image doubled) when the session is
    plain (:func:`plain_session`), their features in ``database`` in place of the first ones;
    returns the files detected again. Nothing is done, at no cost, when the frames are not
    plain or ``first_octave`` is already -1."""
    import pycolmap

    if cfg.first_octave < 0 or cfg.plain_keypoints_share <= 0:
        return []
    db = pycolmap.Database.open(str(database))
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        counts = [db.num_keypoints_for_image(ids[f]) if f in ids else 0 for f in files]
    finally:
        db.close()
    if not plain_session(counts, cfg):
        return []
    plain = [f for f in files if f in ids]
    finer = work_dir / "plain.db"
    finer.unlink(missing_ok=True)
    pycolmap.Database.open(str(finer)).close()
    opts2 = copy.deepcopy(opts)  # one octave finer
    opts2.sift.first_octave = cfg.first_octave - 1
    pycolmap.import_images(finer, image_dir, pycolmap.CameraMode.SINGLE, plain, reader)
    pycolmap.extract_features(
        finer, image_dir, image_names=plain, camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader, extraction_options=opts2, device=pycolmap.Device.cpu,
    )
    new: dict[str, tuple[np.ndarray, object]] = {}
    db2 = pycolmap.Database.open(str(finer))
    try:
        for im in db2.read_all_images():
            if db2.exists_keypoints(im.image_id):
                new[im.name] = (db2.read_keypoints(im.image_id), db2.read_descriptors(im.image_id))
    finally:
        db2.close()
    finer.unlink(missing_ok=True)
    # the database cannot replace one image's features: every image's are written again
    db = pycolmap.Database.open(str(database))
    try:
        kept = {}
        for name, image_id in ids.items():
            if name not in new and db.exists_keypoints(image_id):
                kept[image_id] = (db.read_keypoints(image_id), db.read_descriptors(image_id))
        db.clear_keypoints()
        db.clear_descriptors()
        for name, image_id in ids.items():
            kp_desc = new.get(name) or kept.get(image_id)
            if kp_desc is not None:
                db.write_keypoints(image_id, kp_desc[0])
                db.write_descriptors(image_id, kp_desc[1])
    finally:
        db.close()
    before = [c for f, c in zip(files, counts, strict=True) if f in new]
    after = [len(new[f][0]) for f in plain if f in new]
    log.info("features: the frames are plain at the working size (median %d keypoints, "
             "fewer than %.0f): %d detected again on the image doubled, median %d keypoints",
             int(np.median(before)) if before else 0,
             cfg.plain_keypoints_share * cfg.max_num_features, len(new),
             int(np.median(after)) if after else 0)
    return [f for f in plain if f in new]


def _check_size(img: np.ndarray, camera: Camera, path: Path) -> None:
    h, w = img.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise InputError(
            f"{path}: frame is {w}x{h} but camera.json says {camera.width}x{camera.height}"
        )


def frame_mask(path: Path, camera: Camera, size: tuple[int, int],
               fov: np.ndarray | None) -> np.ndarray:
    """A frame's mask (0 = glint) at working ``size``, a pixel valid only where every source
    pixel was; intersected with the working field-of-view mask ``fov``. A missing file means
    no glints in that frame."""
    m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
    if m is None:
        return fov if fov is not None else np.full(size[::-1], 255, np.uint8)
    if m.shape != (camera.height, camera.width):
        raise InputError(f"{path}: mask is {m.shape[1]}x{m.shape[0]} but camera.json says "
                         f"{camera.width}x{camera.height}")
    m = (m > 127).astype(np.uint8) * 255
    if m.shape[::-1] != size:
        m = cv2.resize(m, size, interpolation=cv2.INTER_AREA)
        m = (m > 250).astype(np.uint8) * 255
    return m if fov is None else np.minimum(m, fov)


def _working_mask(
    mask_path: Path | None, camera: Camera, size: tuple[int, int], scale: float, cfg: SfmConfig
) -> np.ndarray | None:
    """The field-of-view mask at working size (255 = use), eroded by ``cfg.mask_erode_px``."""
    if mask_path is None or not mask_path.is_file():
        return None
    mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        raise InputError(f"{mask_path}: cannot read mask")
    if mask.shape != (camera.height, camera.width):
        raise InputError(
            f"{mask_path}: mask is {mask.shape[1]}x{mask.shape[0]} but camera.json says "
            f"{camera.width}x{camera.height}"
        )
    mask = (mask > 127).astype(np.uint8) * 255
    if scale != 1.0:
        mask = cv2.resize(mask, size, interpolation=cv2.INTER_AREA)
        mask = (mask > 250).astype(np.uint8) * 255
    erode = round(cfg.mask_erode_px * scale)
    if erode > 0:
        mask = cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode + 1,) * 2))
    if not mask.any():
        raise InputError(f"{mask_path}: the mask leaves no valid pixels")
    return mask
