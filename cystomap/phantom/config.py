"""Configuration of the synthetic bladder phantom (``phantom:`` section of the config)."""

from __future__ import annotations

from dataclasses import dataclass

from cystomap.errors import InputError
from cystomap.settings import setting, validate

TEXTURE_MODES = ("procedural", "mosaic")
TEXTURE_FAMILIES = ("A", "B", "C")  # defined in cystomap.phantom.texture.TEXTURE_FAMILIES
LESION_KINDS = ("painted", "papillary", "cis", "scar", "perivascular")
LESION_SITES = ("any", "seam", "pole", "neck")
TRAJECTORIES = ("sweep", "recording")


@dataclass(frozen=True)
class PhantomConfig:
    """Everything that defines a phantom study; two sessions of one bladder share it.

    Every random choice is drawn from numpy Generators seeded by ``seed`` (one stream per
    purpose and session), so equal configs give bit-identical outputs.
    """

    # Seed of shape, texture, lesions and trajectories.
    seed: int = setting(7, ">= 0")
    # Frames in each session's video.
    n_frames: int = setting(124, ">= 2")
    # Frame rate of the rendered videos.
    fps: float = setting(10.0, "> 0")
    # Camera timing: "sweep" = the scan path in n_frames evenly spaced steps; "recording" = the
    # same path on a urologist's timing (slow scan, the scope held still 1.2-3 s, taken back over
    # the stretch just seen, bent fast; hand tremor; cystomap.phantom.recording), its ground truth
    # as for a sweep (poses per video frame; truth.json frames.motion labels each frame scan,
    # pause, bend or back). Motion blur (motion_blur_px) follows the image speed: the bends.
    trajectory: str = setting("sweep", choices=TRAJECTORIES)
    # Recording: its length in seconds at fps (frames = round(duration_s * fps)); 0 = n_frames.
    duration_s: float = setting(0.0, ">= 0")
    # Overall bladder size (mm) along its three axes.
    size_mm: tuple[float, float, float] = setting((170.0, 130.0, 110.0), "> 0")
    # Diameter of the aperture to the urethra (mm).
    aperture_mm: float = setting(40.0, "> 0")
    # Finest texture scale (mm); 0.4 = low texture, no fine vessels.
    texture_detail_mm: float = setting(0.1, "[0.02, 5]")
    # Diameters (mm) of the lesions painted into session 2.
    lesion_diameters_mm: tuple[float, ...] = setting((5.0, 10.0, 15.0, 20.0, 25.0, 30.0), "> 0")
    # Illumination gain of session 2 relative to session 1.
    session2_gain: float = setting(0.85, "> 0")
    # Deformation of session 2 (0.07 = 7 %: anisotropic scale and smooth radial warp).
    deformation: float = setting(0.0, "[0, 0.25]")
    # Maximum motion-blur length (px); 0 = none.
    motion_blur_px: float = setting(0.0, ">= 0")
    # Render specular glints.
    specular: bool = False
    # Share of defocused or black frames inserted.
    bad_frame_fraction: float = setting(0.0, "[0, 0.5]")
    # Sensor noise (8-bit digital numbers).
    noise_sigma: float = setting(2.0, ">= 0")
    # Code video.mp4 losslessly (FFV1, about 40x larger) instead of with mp4v, whose fixed
    # quantiser removes the fine low-contrast texture at low resolutions: at 640x360, mp4v makes
    # SfM unreliable (40-90 % of frames registered), FFV1 keeps every frame.
    lossless_video: bool = False
    # Relative amplitude of the smooth irregularity of the wall (0 = ellipsoid + neck).
    irregularity: float = setting(0.045, "[0, 0.12]")
    # Length of the urethra tube below the aperture (mm).
    urethra_length_mm: float = setting(30.0, "> 0")
    # Target edge length of the true wall's triangle mesh (mm).
    mesh_edge_mm: float = setting(1.5, "[0.3, 5]")
    # Texels per cube-map face edge of the texture; 0 = from texture_detail_mm (at most 2048).
    cube_face_px: int = setting(0, "[0, 4096]")
    # Height of the true albedo.png and seen.png (width is twice this).
    atlas_height: int = setting(1024, "[32, 8192]")
    # Frames rendered concurrently; 0 = the machine's cores, at most 2.
    threads: int = setting(0, ">= 0")
    # Wall texture: "procedural" = the baked mucosa; "mosaic" = the wall tiled with a few patches
    # of that mucosa, each repeated many times with random rotation, mirroring, anisotropic
    # stretch and tint (a printed photo-mosaic phantom: the same patch in many places).
    texture_mode: str = setting("procedural", choices=TEXTURE_MODES)
    # Mosaic: number of distinct patches.
    mosaic_patches: int = setting(4, "[1, 64]")
    # Mosaic: patch edge on the wall (mm); tiles lie about 0.6 patch edges apart.
    mosaic_patch_mm: float = setting(25.0, "[3, 80]")
    # Radial distortion k1 of the rendered lens, replacing the camera's (null = the camera's own;
    # other coefficients and the pinhole part are kept). With a diagonal_fov_deg-only camera, e.g.
    # -0.2, the pipeline must estimate the distortion; camera.json holds the rendered lens.
    lens_k1: float | None = setting(None, "[-0.45, 0.3]")
    # Diameter of the scope's round image as a share of the frame's height (0 = the image fills
    # the frame): a cystoscope whose image circle sits in a wider black frame (0.95 in a
    # 1920x1080 frame lights 40 % of it; issue 12's in vivo recording: 43 %). Outside the
    # circle the frame is black but for the sensor noise; seen.png counts only what is inside.
    image_circle: float = setting(0.0, "[0, 3]")
    # Render at this share of the camera's size and enlarge each frame to it (bilinear) before
    # it is coded: 0.5 traces a quarter of the rays (for long 1080p recordings), at the cost of
    # the texture finer than the rendered pixels; truth.json and camera.json are the video's.
    render_scale: float = setting(1.0, "(0, 1]")
    # Texture family of the subject; empty = the fixed default wall. A = pink, fine mottling, the
    # default vessel network; B = pale, coarse strong blotches, sparse faint vessels, little
    # grain; C = red (inflamed), fine strong mottling, dense dark vessels, strong grain. Mottling
    # scale and contrast, vessel density and colour and grain are drawn per seed within the
    # family's ranges (truth.json texture.params).
    texture_family: str = setting("", choices=("", *TEXTURE_FAMILIES))
    # Per-session photometry drawn from the seed, scaled by this (0 = none, 1 = nominal): white
    # balance (log-gain std 0.06 per channel), exposure bias (log std 0.15), auto-gain smoothing
    # weight (0.5 +- 0.35) and flicker (log std 0.02), vignetting exponent (3 -1.5..+2) and
    # distance fall-off exponent (2 +- 0.4); recorded in truth.json photometry.
    photometric_variation: float = setting(0.0, "[0, 3]")
    # Kind of each lesion: one per lesion_diameters_mm, or else drawn per lesion from this list
    # (seeded); empty = all painted. painted = papillary look, flat (colour only); papillary = the
    # same, raised into the cavity (relief 0.35 x diameter, at most 6 mm, in session 2's
    # geometry); cis = flat red velvety low-contrast patch; scar = pale elongated patch;
    # perivascular = red patch beside a vessel shown in both sessions. lesions.csv records kind,
    # site and height_mm.
    lesion_kinds: tuple[str, ...] = setting((), choices=LESION_KINDS)
    # Site of each lesion (same rule as lesion_kinds); empty = all any. seam = across the atlas's
    # +-180 deg azimuth seam; pole = over the top pole; neck = its edge about 4 deg beyond the
    # aperture.
    lesion_sites: tuple[str, ...] = setting((), choices=LESION_SITES)

    @property
    def frame_count(self) -> int:
        """Frames in each session's video: ``duration_s * fps`` for a recording, else
        ``n_frames``."""
        if self.trajectory == "recording" and self.duration_s > 0:
            return max(2, round(self.duration_s * self.fps))
        return self.n_frames

    def __post_init__(self) -> None:
        problems = []
        try:
            validate(self, "phantom")
        except ValueError as exc:
            problems.append(str(exc))
        if len(self.size_mm) == 3 and not self.aperture_mm < 0.6 * min(self.size_mm):
            problems.append("aperture_mm must be well below the smallest size")
        if len(self.size_mm) == 3 and any(
            d > 0.35 * min(self.size_mm) for d in self.lesion_diameters_mm
        ):
            problems.append("lesion_diameters_mm too large for the bladder")
        if self.cube_face_px and not (64 <= self.cube_face_px and self.cube_face_px % 16 == 0):
            problems.append("cube_face_px must be 0 or a multiple of 16 in [64, 4096]")
        if problems:
            raise InputError("phantom config: " + "; ".join(problems))
