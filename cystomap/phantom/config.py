"""Configuration of the synthetic bladder phantom (``phantom:`` section of the config)."""

from __future__ import annotations

from dataclasses import dataclass

from cystomap.errors import InputError
from cystomap.settings import setting, validate

TEXTURE_MODES = ("procedural", "mosaic")
TEXTURE_FAMILIES = ("A", "B", "C")  # defined in cystomap.phantom.texture.TEXTURE_FAMILIES
LESION_KINDS = ("painted", "papillary", "cis", "scar", "perivascular")
LESION_SITES = ("any", "seam", "pole", "neck")


@dataclass(frozen=True)
class PhantomConfig:
    """Everything that defines a phantom study; two sessions of one bladder share it.

    Every random choice is drawn from numpy Generators seeded by ``seed`` (one stream per
    purpose and session), so equal configs give bit-identical outputs.
    """

    seed: int = setting(7, ">= 0")
    # frames in each session's video
    n_frames: int = setting(124, ">= 2")
    # frame rate written into video.mp4 (and truth.json)
    fps: float = setting(10.0, "> 0")
    # overall size (bounding box) of the bladder along world x, y, z, in mm
    size_mm: tuple[float, float, float] = (170.0, 130.0, 110.0)
    # diameter of the aperture (bladder neck) into the urethra tube, in mm
    aperture_mm: float = 40.0
    # finest texture scale in mm; 0.4 = "low texture" (no fine vessels, coarse grain)
    texture_detail_mm: float = setting(0.1, "[0.02, 5]")
    # diameters of the six (or however many) lesions painted into session 2, in mm
    lesion_diameters_mm: tuple[float, ...] = (5.0, 10.0, 15.0, 20.0, 25.0, 30.0)
    # illumination gain of session 2 (multiplies its 8-bit output after auto-exposure)
    session2_gain: float = setting(0.85, "> 0")
    # session 2 deformation magnitude (0.07 = 7 %): anisotropic scale + smooth radial warp
    deformation: float = setting(0.0, "[0, 0.25]")
    # maximum motion-blur length in pixels (the fastest frame gets it); 0 = none
    motion_blur_px: float = setting(0.0, ">= 0")
    # small saturated glints where the wet wall faces the camera
    specular: bool = False
    # share of frames replaced by defocused or black frames (poses stay true)
    bad_frame_fraction: float = setting(0.0, "[0, 0.5]")
    # Gaussian sensor noise, standard deviation in 8-bit DN
    noise_sigma: float = setting(2.0, ">= 0")
    # code video.mp4 losslessly (FFV1, ~40x larger) instead of with mp4v, whose fixed
    # quantiser removes the fine low-contrast texture at low resolutions (e.g. 640x360)
    lossless_video: bool = False
    # relative amplitude of the smooth irregularity of the wall (0 = ellipsoid + neck)
    irregularity: float = setting(0.045, "[0, 0.12]")
    # length of the urethra tube below the aperture, in mm
    urethra_length_mm: float = setting(30.0, "> 0")
    # target edge length of the wall triangle mesh, in mm
    mesh_edge_mm: float = setting(1.5, "[0.3, 5]")
    # texels per cube-map face edge; 0 = automatic from texture_detail_mm (<= 2048)
    cube_face_px: int = 0
    # height of albedo.png / seen.png (width is twice this)
    atlas_height: int = setting(1024, "[32, 8192]")
    # rendering threads (frames rendered concurrently); 0 = os.cpu_count() capped at 2
    threads: int = setting(0, ">= 0")
    # wall texture: "procedural" (the baked mucosa) or "mosaic" (the wall tiled with a few
    # patches of that mucosa, each repeated many times with random rotation, mirroring,
    # anisotropic stretch and tint: the failure class of a printed photo-mosaic phantom)
    texture_mode: str = setting("procedural", choices=TEXTURE_MODES)
    # mosaic: number of distinct patches
    mosaic_patches: int = setting(4, "[1, 64]")
    # mosaic: patch edge length on the wall in mm (tiles are about 0.6x this apart)
    mosaic_patch_mm: float = setting(25.0, "[3, 80]")
    # radial distortion k1 of the rendered lens, replacing the camera's (None = the camera's
    # own); with a diagonal_fov_deg-only camera the pipeline must then estimate it. The
    # rendered lens is written to camera.json (and truth.json "lens")
    lens_k1: float | None = None
    # texture family of the subject ("" = the fixed default wall; "A" pink/fine, "B" pale/
    # coarse blotches/sparse vessels, "C" red/dense vessels/strong grain): mottling scale and
    # contrast, vessel density and colour, grain drawn per seed within the family's ranges
    texture_family: str = setting("", choices=("", *TEXTURE_FAMILIES))
    # per-session photometry drawn from the seed (0 = none; 1 = the nominal ranges): white
    # balance, exposure bias, auto-gain smoothing and flicker, vignetting and fall-off exponents
    photometric_variation: float = setting(0.0, "[0, 3]")
    # kind of each lesion (one per lesion_diameters_mm, or a list drawn from per lesion, seeded):
    # painted (papillary look, flat: the default), papillary (raised: relief in the geometry),
    # cis (flat red velvety patch, low contrast), scar (pale), perivascular (red patch beside
    # a vessel that is in both sessions); () = all painted
    lesion_kinds: tuple[str, ...] = ()
    # site of each lesion (same rule): any, seam (across the atlas's +-180 deg azimuth seam),
    # pole (over the top pole of the atlas), neck (just beside the aperture); () = all any
    lesion_sites: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        problems = []
        try:
            validate(self, "phantom")
        except ValueError as exc:
            problems.append(str(exc))
        if len(self.size_mm) != 3 or min(self.size_mm) <= 0:
            problems.append("size_mm must be three positive lengths")
        elif not 0 < self.aperture_mm < 0.6 * min(self.size_mm):
            problems.append("aperture_mm must be positive and well below the smallest size")
        if any(d <= 0 for d in self.lesion_diameters_mm):
            problems.append("lesion_diameters_mm must be positive")
        if len(self.size_mm) == 3 and any(
            d > 0.35 * min(self.size_mm) for d in self.lesion_diameters_mm
        ):
            problems.append("lesion_diameters_mm too large for the bladder")
        if self.cube_face_px and not (64 <= self.cube_face_px <= 4096 and self.cube_face_px % 16 == 0):
            problems.append("cube_face_px must be 0 or a multiple of 16 in [64, 4096]")
        for key, names in (("lesion_kinds", LESION_KINDS), ("lesion_sites", LESION_SITES)):
            bad = [k for k in getattr(self, key) if k not in names]
            if bad:
                problems.append(f"{key}: unknown {', '.join(bad)} (known: {', '.join(names)})")
        if self.lens_k1 is not None and not -0.45 <= self.lens_k1 <= 0.3:
            problems.append("lens_k1 must be null or in [-0.45, 0.3]")
        if problems:
            raise InputError("phantom config: " + "; ".join(problems))
