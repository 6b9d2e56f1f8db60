"""Configuration of the synthetic bladder phantom (``phantom:`` section of the config)."""

from __future__ import annotations

from dataclasses import dataclass

from cystomap.errors import InputError

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

    seed: int = 7
    # frames in each session's video
    n_frames: int = 124
    # frame rate written into video.mp4 (and truth.json)
    fps: float = 10.0
    # overall size (bounding box) of the bladder along world x, y, z, in mm
    size_mm: tuple[float, float, float] = (170.0, 130.0, 110.0)
    # diameter of the aperture (bladder neck) into the urethra tube, in mm
    aperture_mm: float = 40.0
    # finest texture scale in mm; 0.4 = "low texture" (no fine vessels, coarse grain)
    texture_detail_mm: float = 0.1
    # diameters of the six (or however many) lesions painted into session 2, in mm
    lesion_diameters_mm: tuple[float, ...] = (5.0, 10.0, 15.0, 20.0, 25.0, 30.0)
    # illumination gain of session 2 (multiplies its 8-bit output after auto-exposure)
    session2_gain: float = 0.85
    # session 2 deformation magnitude (0.07 = 7 %): anisotropic scale + smooth radial warp
    deformation: float = 0.0
    # maximum motion-blur length in pixels (the fastest frame gets it); 0 = none
    motion_blur_px: float = 0.0
    # small saturated glints where the wet wall faces the camera
    specular: bool = False
    # share of frames replaced by defocused or black frames (poses stay true)
    bad_frame_fraction: float = 0.0
    # Gaussian sensor noise, standard deviation in 8-bit DN
    noise_sigma: float = 2.0
    # code video.mp4 losslessly (FFV1, ~40x larger) instead of with mp4v, whose fixed
    # quantiser removes the fine low-contrast texture at low resolutions (e.g. 640x360)
    lossless_video: bool = False
    # relative amplitude of the smooth irregularity of the wall (0 = ellipsoid + neck)
    irregularity: float = 0.045
    # length of the urethra tube below the aperture, in mm
    urethra_length_mm: float = 30.0
    # target edge length of the wall triangle mesh, in mm
    mesh_edge_mm: float = 1.5
    # texels per cube-map face edge; 0 = automatic from texture_detail_mm (<= 2048)
    cube_face_px: int = 0
    # height of albedo.png / seen.png (width is twice this)
    atlas_height: int = 1024
    # rendering threads (frames rendered concurrently); 0 = os.cpu_count() capped at 2
    threads: int = 0
    # wall texture: "procedural" (the baked mucosa) or "mosaic" (the wall tiled with a few
    # patches of that mucosa, each repeated many times with random rotation, mirroring,
    # anisotropic stretch and tint: the failure class of a printed photo-mosaic phantom)
    texture_mode: str = "procedural"
    # mosaic: number of distinct patches
    mosaic_patches: int = 4
    # mosaic: patch edge length on the wall in mm (tiles are about 0.6x this apart)
    mosaic_patch_mm: float = 25.0
    # radial distortion k1 of the rendered lens, replacing the camera's (None = the camera's
    # own); with a diagonal_fov_deg-only camera the pipeline must then estimate it. The
    # rendered lens is written to camera.json (and truth.json "lens")
    lens_k1: float | None = None
    # texture family of the subject ("" = the fixed default wall; "A" pink/fine, "B" pale/
    # coarse blotches/sparse vessels, "C" red/dense vessels/strong grain): mottling scale and
    # contrast, vessel density and colour, grain drawn per seed within the family's ranges
    texture_family: str = ""
    # per-session photometry drawn from the seed (0 = none; 1 = the nominal ranges): white
    # balance, exposure bias, auto-gain smoothing and flicker, vignetting and fall-off exponents
    photometric_variation: float = 0.0
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
        if self.n_frames < 2:
            problems.append("n_frames must be >= 2")
        if self.fps <= 0:
            problems.append("fps must be > 0")
        if len(self.size_mm) != 3 or min(self.size_mm) <= 0:
            problems.append("size_mm must be three positive lengths")
        elif not 0 < self.aperture_mm < 0.6 * min(self.size_mm):
            problems.append("aperture_mm must be positive and well below the smallest size")
        if not 0.02 <= self.texture_detail_mm <= 5.0:
            problems.append("texture_detail_mm must be in [0.02, 5]")
        if any(d <= 0 for d in self.lesion_diameters_mm):
            problems.append("lesion_diameters_mm must be positive")
        if len(self.size_mm) == 3 and any(
            d > 0.35 * min(self.size_mm) for d in self.lesion_diameters_mm
        ):
            problems.append("lesion_diameters_mm too large for the bladder")
        if self.session2_gain <= 0:
            problems.append("session2_gain must be > 0")
        if not 0 <= self.deformation <= 0.25:
            problems.append("deformation must be in [0, 0.25]")
        if self.motion_blur_px < 0:
            problems.append("motion_blur_px must be >= 0")
        if not 0 <= self.bad_frame_fraction <= 0.5:
            problems.append("bad_frame_fraction must be in [0, 0.5]")
        if self.noise_sigma < 0:
            problems.append("noise_sigma must be >= 0")
        if not 0 <= self.irregularity <= 0.12:
            problems.append("irregularity must be in [0, 0.12]")
        if self.urethra_length_mm <= 0:
            problems.append("urethra_length_mm must be > 0")
        if not 0.3 <= self.mesh_edge_mm <= 5:
            problems.append("mesh_edge_mm must be in [0.3, 5]")
        if self.cube_face_px and not (64 <= self.cube_face_px <= 4096 and self.cube_face_px % 16 == 0):
            problems.append("cube_face_px must be 0 or a multiple of 16 in [64, 4096]")
        if not 32 <= self.atlas_height <= 8192:
            problems.append("atlas_height must be in [32, 8192]")
        if self.threads < 0:
            problems.append("threads must be >= 0")
        if self.texture_mode not in TEXTURE_MODES:
            problems.append(f"texture_mode must be one of {', '.join(TEXTURE_MODES)}")
        if not 1 <= self.mosaic_patches <= 64:
            problems.append("mosaic_patches must be in [1, 64]")
        if not 3.0 <= self.mosaic_patch_mm <= 80.0:
            problems.append("mosaic_patch_mm must be in [3, 80]")
        if self.texture_family not in ("", *TEXTURE_FAMILIES):
            problems.append(f"texture_family must be empty or one of {', '.join(TEXTURE_FAMILIES)}")
        if not 0 <= self.photometric_variation <= 3:
            problems.append("photometric_variation must be in [0, 3]")
        for key, names in (("lesion_kinds", LESION_KINDS), ("lesion_sites", LESION_SITES)):
            bad = [k for k in getattr(self, key) if k not in names]
            if bad:
                problems.append(f"{key}: unknown {', '.join(bad)} (known: {', '.join(names)})")
        if self.lens_k1 is not None and not -0.45 <= self.lens_k1 <= 0.3:
            problems.append("lens_k1 must be null or in [-0.45, 0.3]")
        if problems:
            raise InputError("phantom config: " + "; ".join(problems))
