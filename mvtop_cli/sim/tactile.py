"""GelSight-like tactile image synthesis from a gel indentation map (pure numpy + OpenCV).

The model, in the order it is applied:

1. The indentation map (how far the gel surface is pushed towards the sensor's camera,
   metres, 0 where the gel is undeformed) gives the gel surface: where the rigid object
   touches, the gel takes its shape; around it, the elastomer relaxes over a fraction of
   a millimetre, modelled as the larger of the indentation and its Gaussian blur
   (``gel_surface_m``). So a press also changes the image in a narrow band around the
   contact, as on a real sensor.
2. The surface normal follows from the gradient of that surface. Three coloured LEDs
   light the gel at a grazing angle from different sides (red from the bottom left,
   green from the top left, blue from the right, as in the real GelSight R1.5 frames
   of the Taxim data set), so each colour channel responds to the slope towards its
   LED: a Lambertian ratio ``max(n . l, 0) / (n0 . l)`` against the flat gel's ``n0``.
3. The relative change, softly saturated (``tanh``) and slightly mixed between channels
   (LED spectra overlap the camera's colour filters), scales the no-contact frame:
   the LEDs' illumination at a pixel is what the background shows there.
4. The camera's point spread (a small Gaussian on the shading), Gaussian sensor noise,
   rounding and clipping to uint8.

A flat, undeformed pixel therefore shows exactly the background plus noise. Both
smoothing kernels are truncated at 3 sigma, so the image changes only within
``ceil(3 * gel_blur_mm / mm_per_px) + 1 + ceil(3 * optics_blur_px)`` pixels of an
indented pixel (the +1 is the central-difference gradient).

Against the real GelSight R1.5 frames of the Taxim data set (120x160, 0.1245 mm/px):
the coarse colour layout of ``make_background`` correlates at ~0.9 per channel with the
real no-contact frame, and a 2 mm-radius ball pressed 1.2 mm changes the image by about
as much as the real presses (99.5th percentile of the colour change ~90 DN vs ~88 DN).
The synthetic frames are cleaner than the real ones: no interference rings in the
difference to the no-contact frame, no JPEG artefacts.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

# LED azimuths in the image plane [deg], measured from +x (right) towards +y (down).
# Chosen so that the coloured rims and the no-contact frame look like the real
# GelSight R1.5 images (Taxim): green upper left, blue right, red lower left.
_LED_AZIMUTH_DEG = {"red": 125.0, "green": 235.0, "blue": 0.0}

# How much each LED leaks into the other colour channels (rows: camera channel R, G, B;
# columns: red, green, blue LED). Real GelSight rims are vivid but not pure colours.
_CHANNEL_MIXING = np.array(
    [
        [1.00, 0.10, 0.15],
        [0.10, 1.00, 0.10],
        [0.12, 0.15, 1.00],
    ]
)


def gel_surface_m(indentation_m: np.ndarray, mm_per_px: float, gel_blur_mm: float = 0.25) -> np.ndarray:
    """The gel surface displacement for an indentation: ``max(indentation, blur(indentation))``.

    Inside the contact the gel follows the object; around it the blur's tail is the
    elastomer relaxing back to the undeformed plane.

    Parameters
    ----------
    indentation_m : (H, W) float
        Indentation of the gel [m], >= 0, 0 = undeformed.
    mm_per_px : float
        Size of one pixel on the gel [mm].
    gel_blur_mm : float
        Standard deviation of the Gaussian spread [mm]; 0 disables it. The kernel is
        truncated at 3 standard deviations, so far-away pixels stay exactly 0.

    Returns
    -------
    surface_m : (H, W) float32
        The gel surface displacement towards the camera [m], >= ``indentation_m``.
    """
    indentation = _check_indentation(indentation_m)
    if not mm_per_px > 0:
        raise ValueError(f"mm_per_px must be > 0, got {mm_per_px!r}")
    if gel_blur_mm < 0:
        raise ValueError(f"gel_blur_mm must be >= 0, got {gel_blur_mm!r}")
    sigma_px = gel_blur_mm / mm_per_px
    if sigma_px < 1e-3:
        return indentation.copy()
    half = max(1, math.ceil(3.0 * sigma_px))
    # Zero padding: outside the image the gel is undeformed.
    spread = cv2.GaussianBlur(indentation, (2 * half + 1, 2 * half + 1), sigma_px, borderType=cv2.BORDER_CONSTANT)
    # Where the rigid object touches, the gel takes its shape; around it, the gel relaxes.
    return np.maximum(indentation, spread)


def render_tactile_image(
    indentation_m: np.ndarray,
    mm_per_px: float,
    background: np.ndarray,
    rng: np.random.Generator,
    noise_std: float = 1.5,
    *,
    gel_blur_mm: float = 0.25,
    light_elevation_deg: float = 30.0,
    response_gain: float = 0.6,
    saturation: float = 0.7,
    optics_blur_px: float = 0.7,
) -> np.ndarray:
    """Render the tactile image a GelSight-like sensor would see for an indentation.

    Parameters
    ----------
    indentation_m : (H, W) float
        Indentation of the gel towards the sensor's camera [m], >= 0, 0 = undeformed.
    mm_per_px : float
        Size of one pixel on the gel [mm] (GelSight R1.5 at 160x120: 0.1245).
    background : (H, W, 3) uint8
        The no-contact frame, RGB (e.g. from ``make_background``).
    rng : numpy.random.Generator
        Source of the sensor noise; the same seed gives the same image.
    noise_std : float
        Standard deviation of the per-pixel, per-channel Gaussian noise [DN].
    gel_blur_mm : float
        Spread of the deformation in the elastomer [mm] (see ``gel_surface_m``).
    light_elevation_deg : float
        Elevation of the LEDs above the gel plane [deg]; low = grazing, strong contrast.
    response_gain : float
        Relative brightness change per unit change of the Lambertian ratio.
    saturation : float
        Largest relative brightness change (soft limit, ``tanh``), a mild non-linearity.
    optics_blur_px : float
        Standard deviation of the camera's point spread [px], applied to the shading
        (truncated at 3 sigma); 0 disables.

    Returns
    -------
    image : (H, W, 3) uint8
        The tactile image, RGB.
    """
    indentation = _check_indentation(indentation_m)
    background = _check_background(background, indentation.shape)
    if noise_std < 0:
        raise ValueError(f"noise_std must be >= 0, got {noise_std!r}")
    if not 0.0 < light_elevation_deg < 90.0:
        raise ValueError(f"light_elevation_deg must be in (0, 90), got {light_elevation_deg!r}")
    if saturation <= 0:
        raise ValueError(f"saturation must be > 0, got {saturation!r}")
    if optics_blur_px < 0:
        raise ValueError(f"optics_blur_px must be >= 0, got {optics_blur_px!r}")

    surface_mm = gel_surface_m(indentation, mm_per_px, gel_blur_mm).astype(np.float64) * 1e3
    # Slopes of the surface (height towards the camera) along image x and y.
    dh_dy, dh_dx = np.gradient(surface_mm, mm_per_px)
    inv_norm = 1.0 / np.sqrt(1.0 + dh_dx**2 + dh_dy**2)
    normals = np.stack([-dh_dx * inv_norm, -dh_dy * inv_norm, inv_norm], axis=-1)

    elevation = math.radians(light_elevation_deg)
    flat_response = math.sin(elevation)  # n0 . l for the undeformed gel, n0 = (0, 0, 1)
    ratios = []
    for name in ("red", "green", "blue"):
        azimuth = math.radians(_LED_AZIMUTH_DEG[name])
        light = np.array(
            [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), flat_response]
        )
        ratios.append(np.maximum(normals @ light, 0.0) / flat_response - 1.0)
    led_change = np.stack(ratios, axis=-1)  # 0 exactly on flat gel
    channel_change = led_change @ _CHANNEL_MIXING.T
    relative = saturation * np.tanh(response_gain * channel_change / saturation)
    if optics_blur_px > 0:
        # The camera's point spread: also hides the pixel staircase of straight edges.
        half = max(1, math.ceil(3.0 * optics_blur_px))
        relative = cv2.GaussianBlur(
            relative, (2 * half + 1, 2 * half + 1), optics_blur_px, borderType=cv2.BORDER_CONSTANT
        )

    image = background.astype(np.float64) * (1.0 + relative)
    if noise_std > 0:
        image += rng.normal(0.0, noise_std, size=image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def make_background(
    height: int,
    width: int,
    rng: np.random.Generator,
    *,
    markers: bool = True,
    marker_pitch_frac: float = 0.07,
    vignetting: float = 0.12,
) -> np.ndarray:
    """A no-contact GelSight frame: coloured LED gradients, vignetting, faint markers.

    The red LED lights the gel from the lower left (with a glare spot in that corner),
    the green one from the upper left and the blue one from the right, each as a broad
    falloff over the gel, like the real GelSight R1.5 frame of the Taxim data set.
    Positions, strengths and a faint low-frequency non-uniformity of the gel vary with
    ``rng``. The frame is noise free; render a zero indentation with
    ``render_tactile_image`` to get a noisy no-contact capture.

    Parameters
    ----------
    height, width : int
        Image size [px].
    rng : numpy.random.Generator
        Source of the per-sensor variation.
    markers : bool
        Draw faint dark marker dots on a jittered square grid.
    marker_pitch_frac : float
        Marker spacing as a fraction of the image width.
    vignetting : float
        Relative darkening at the image corners.

    Returns
    -------
    background : (height, width, 3) uint8
        RGB.
    """
    if height < 2 or width < 2:
        raise ValueError(f"background size must be at least 2x2, got {height}x{width}")
    aspect = width / height
    # Normalised coordinates: v in [0, 1] down the image, u in [0, aspect] across it.
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    v = (v + 0.5) / height
    u = (u + 0.5) / height

    def jitter(scale: float) -> float:
        return float(rng.uniform(-scale, scale))

    # (position (u, v), spread, peak increase per channel R, G, B) of each LED's light.
    leds = [
        ((0.10 * aspect + jitter(0.05), 1.10 + jitter(0.05)), 0.45, (150.0, 10.0, 0.0)),
        ((0.15 * aspect + jitter(0.05), -0.15 + jitter(0.05)), 0.50, (5.0, 100.0, 5.0)),
        ((1.05 * aspect + jitter(0.05), 0.55 + jitter(0.08)), 0.50, (15.0, 0.0, 70.0)),
    ]
    base = np.array([112.0, 108.0, 112.0]) + rng.uniform(-6.0, 6.0, size=3)
    image = np.broadcast_to(base, (height, width, 3)).copy()
    for (pu, pv), spread, peak in leds:
        falloff = np.exp(-((u - pu) ** 2 + (v - pv) ** 2) / (2.0 * spread**2))
        strength = 1.0 + jitter(0.1)
        image += strength * falloff[..., None] * np.asarray(peak)

    # Glare of the red LED in the lower-left corner (yellow-white, saturating).
    glare = np.exp(-((u - 0.02 * aspect) ** 2 + (v - 1.0) ** 2) / (2.0 * 0.06**2))
    image += glare[..., None] * np.array([60.0, 45.0, 25.0])

    # Faint arcs around the red LED, like the banding of the real frames.
    radius = np.hypot(u - leds[0][0][0], v - leds[0][0][1])
    image += (1.2 * np.sin(2.0 * np.pi * radius / 0.09 + rng.uniform(0, 2 * np.pi)))[..., None]

    # Low-frequency non-uniformity of the gel and its coating.
    texture = rng.normal(0.0, 1.0, size=(height, width, 3))
    sigma_px = 0.06 * height
    texture = cv2.GaussianBlur(texture, (0, 0), sigma_px)
    texture *= 3.0 / max(float(texture.std()), 1e-9)
    image += texture

    # Vignetting of the camera lens.
    r2 = ((u - 0.5 * aspect) ** 2 + (v - 0.5) ** 2) / (0.25 * (aspect**2 + 1.0))
    image *= (1.0 - vignetting * r2)[..., None]

    if markers:
        image *= _marker_shading(height, width, marker_pitch_frac * width, rng)[..., None]
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def sphere_indentation_m(
    shape: tuple[int, int],
    mm_per_px: float,
    center_px: tuple[float, float],
    radius_m: float,
    depth_m: float,
) -> np.ndarray:
    """Indentation of a flat gel pressed by a rigid sphere.

    Parameters
    ----------
    shape : (H, W)
    mm_per_px : float
        Pixel size on the gel [mm].
    center_px : (x, y)
        Where the sphere's lowest point touches [px].
    radius_m, depth_m : float
        Sphere radius and how far it is pressed in [m], ``depth_m <= radius_m``.

    Returns
    -------
    indentation_m : (H, W) float32
        ``depth - (R - sqrt(R^2 - r^2))`` inside the contact circle, 0 outside.
    """
    if not 0.0 <= depth_m <= radius_m:
        raise ValueError(f"depth_m must be in [0, radius_m={radius_m}], got {depth_m!r}")
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    r2_m = ((xx - center_px[0]) ** 2 + (yy - center_px[1]) ** 2) * (mm_per_px * 1e-3) ** 2
    sag_m = radius_m - np.sqrt(np.maximum(radius_m**2 - r2_m, 0.0))
    return np.maximum(depth_m - sag_m, 0.0).astype(np.float32)


def box_indentation_m(
    shape: tuple[int, int],
    mm_per_px: float,
    center_px: tuple[float, float],
    size_m: tuple[float, float],
    depth_m: float,
    angle_rad: float = 0.0,
) -> np.ndarray:
    """Indentation of a flat gel pressed by the flat face of a box (a rectangular punch).

    Parameters
    ----------
    shape : (H, W)
    mm_per_px : float
        Pixel size on the gel [mm].
    center_px : (x, y)
        Centre of the face [px].
    size_m : (width, height)
        Side lengths of the face along its own axes [m].
    depth_m : float
        How far the face is pressed in [m].
    angle_rad : float
        Rotation of the face about the sensor axis, from image +x towards +y [rad].

    Returns
    -------
    indentation_m : (H, W) float32
        ``depth_m`` where a pixel centre lies on the face, 0 elsewhere.
    """
    if depth_m < 0:
        raise ValueError(f"depth_m must be >= 0, got {depth_m!r}")
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    dx_mm = (xx - center_px[0]) * mm_per_px
    dy_mm = (yy - center_px[1]) * mm_per_px
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    along_mm = c * dx_mm + s * dy_mm
    across_mm = -s * dx_mm + c * dy_mm
    inside = (np.abs(along_mm) <= size_m[0] * 5e2) & (np.abs(across_mm) <= size_m[1] * 5e2)
    return np.where(inside, depth_m, 0.0).astype(np.float32)


def _marker_shading(height: int, width: int, pitch_px: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) multiplicative shading, < 1 on faint dark marker dots of a jittered grid."""
    pitch_px = max(pitch_px, 4.0)
    dot_sigma_px = max(0.06 * pitch_px, 0.5)
    cy = np.arange(pitch_px / 2, height, pitch_px)
    cx = np.arange(pitch_px / 2, width, pitch_px)
    centres_y, centres_x = np.meshgrid(cy, cx, indexing="ij")
    centres_y = centres_y + rng.normal(0.0, 0.05 * pitch_px, size=centres_y.shape)
    centres_x = centres_x + rng.normal(0.0, 0.05 * pitch_px, size=centres_x.shape)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    # Nearest grid centre of each pixel (grid jitter is small against the pitch).
    iy = np.clip(np.floor(yy / pitch_px).astype(int), 0, len(cy) - 1)
    ix = np.clip(np.floor(xx / pitch_px).astype(int), 0, len(cx) - 1)
    d2 = (yy - centres_y[iy, ix]) ** 2 + (xx - centres_x[iy, ix]) ** 2
    return 1.0 - 0.06 * np.exp(-d2 / (2.0 * dot_sigma_px**2))


def _check_indentation(indentation_m: np.ndarray) -> np.ndarray:
    indentation = np.asarray(indentation_m, dtype=np.float32)
    if indentation.ndim != 2:
        raise ValueError(f"indentation_m must be (H, W), got shape {indentation.shape}")
    if not np.all(np.isfinite(indentation)):
        raise ValueError("indentation_m has non-finite values")
    if indentation.size and float(indentation.min()) < 0.0:
        raise ValueError(f"indentation_m must be >= 0, got min {float(indentation.min())!r}")
    return indentation


def _check_background(background: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    background = np.asarray(background)
    if background.shape != (*shape, 3):
        raise ValueError(f"background must be {(*shape, 3)} to match indentation_m, got {background.shape}")
    if background.dtype != np.uint8:
        raise ValueError(f"background must be uint8, got {background.dtype}")
    return background
