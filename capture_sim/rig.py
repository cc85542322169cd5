"""The capture rig: display grid, camera, display model and sensor model, loaded from TOML.

A rig is everything about the hardware that the simulator and the reconstructions need; a scene
(its OLAT stack) is captured with one. Presets live in ``configs/rigs/NAME.toml``; a preset either
lists calibrated superpixel positions or describes a panel that ``panel_positions`` builds.
Frames and units follow DESIGN section 2: OpenCV camera frame, metres.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from capture_sim.errors import InputError, check_array, is_whole_number, one_line, warn_once
from capture_sim.toml_io import load_toml

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
RIG_DIR = CONFIG_DIR / "rigs"
DEFAULT_RIG = "dir-odyssey-ark"


MAX_IMAGE_SIDE = 100_000
"""Largest image height or width in pixels (sensors stop well short of it)."""


@dataclass(frozen=True)
class Camera:
    """Pinhole camera of the rig.

    Attributes:
        K_cam: (3, 3) intrinsics in pixels for an image of ``height`` x ``width``.
        height: image rows in pixels.
        width: image columns in pixels.
        exposure_ms: exposure time of one capture of the all-white display, in milliseconds (the
            rig TOML's ``camera.exposure_ms``; the comparison scales it by each pattern set's
            exposure gain), or None where the rig does not give it.
    """

    K_cam: tuple[tuple[float, float, float], ...]
    height: int
    width: int
    exposure_ms: float | None = None

    def __post_init__(self):
        if not (is_whole_number(self.height, 1, MAX_IMAGE_SIDE) and is_whole_number(self.width, 1, MAX_IMAGE_SIDE)):
            raise InputError(f"camera height and width must be whole numbers in 1..{MAX_IMAGE_SIDE}, got {self.height!r} x {self.width!r}")
        if self.exposure_ms is not None:
            object.__setattr__(self, "exposure_ms", camera_exposure_ms(self.exposure_ms))  # frozen: set once, as a float
        k = self.matrix()
        if not (np.isfinite(k).all() and k[0, 0] > 0 and k[1, 1] > 0):
            raise InputError(f"camera fx and fy must be positive and every intrinsic finite, got fx = {float(k[0, 0]):g}, fy = {float(k[1, 1]):g}")

    def matrix(self) -> np.ndarray:
        """(3, 3) float64 intrinsics matrix."""
        return np.asarray(self.K_cam, dtype=np.float64)

    def resized(self, height: int, width: int) -> "Camera":
        """The same camera imaged at another resolution: fx, cx scale with width; fy, cy with height."""
        if height <= 0 or width <= 0:
            raise InputError(f"image size must be positive, got {height} x {width}")
        sx, sy = width / self.width, height / self.height
        k = self.matrix()
        k[0, :] *= sx
        k[1, :] *= sy
        return Camera(K_cam=_as_nested(k), height=height, width=width, exposure_ms=self.exposure_ms)


MAX_LIGHT_DISTANCE_M = 1e6
"""Metres: superpixels farther from the camera are a unit mistake (and their squared distances
leave float32's comfortable range)."""


def check_light_positions(name: str, positions) -> None:
    """Raise ``InputError`` unless ``positions`` is an (R, C, 3) array of finite coordinates of at
    most ``MAX_LIGHT_DISTANCE_M`` in magnitude (a bound on each coordinate: a norm could overflow)."""
    check_array(name, positions, ("R", "C", 3))
    if float(np.abs(np.asarray(positions, dtype=np.float64)).max(initial=0.0)) > MAX_LIGHT_DISTANCE_M:
        raise InputError(f"{name} must have coordinates within {MAX_LIGHT_DISTANCE_M:g} m of the camera (metres, camera frame)")


MAX_NOISE_VARIANCE = 1e12
"""Largest shot gain and squared read noise (full scale 1): a noise std of 1e6 full scales."""

MAX_NOISE_SCALE = 1e6
"""Largest multiplier of a rig's noise variances (``NoiseModel.scaled``): at 1e6 the reference
rig's noise is ~5x full scale (pure noise); far beyond, the simulated variances overflow float32."""


@dataclass(frozen=True)
class NoiseModel:
    """Poisson-Gaussian sensor noise: variance = shot * signal + read_std ** 2 (signal in [0, 1])."""

    shot: float = 1e-4
    """Shot-noise gain a: variance per unit of signal (full scale = 1)."""
    read_std: float = 5e-4
    """Read-noise standard deviation sigma_read, in units of full scale."""

    def __post_init__(self):
        values = (self.shot, self.read_std)
        if not all(isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) and v >= 0 for v in values):
            raise InputError(f"noise shot and read_std must be finite numbers >= 0, got {self.shot!r}, {self.read_std!r}")
        # Far beyond pure noise (std 1 = full scale), and what float32 variances hold with room to spare.
        if self.shot > MAX_NOISE_VARIANCE or self.read_std > math.sqrt(MAX_NOISE_VARIANCE):
            raise InputError(f"noise shot must be at most {MAX_NOISE_VARIANCE:g} and read_std at most {math.sqrt(MAX_NOISE_VARIANCE):g} "
                             f"(full-scale units), got {self.shot!r}, {self.read_std!r}")

    def scaled(self, factor: float) -> "NoiseModel":
        """Noise with both variance terms multiplied by ``factor`` in [0, MAX_NOISE_SCALE] (0 gives
        a noise-free sensor)."""
        check_noise_scale("noise scale", factor)
        try:
            return NoiseModel(shot=self.shot * factor, read_std=self.read_std * math.sqrt(factor))
        except InputError:
            raise InputError(f"noise scale {factor:g} takes this rig's noise (shot {self.shot:g}, read_std {self.read_std:g}) "
                             f"beyond a variance of {MAX_NOISE_VARIANCE:g} full-scale units; use a smaller noise scale") from None


def check_noise_scale(name: str, value) -> None:
    """Raise ``InputError`` unless ``value`` is a number in [0, MAX_NOISE_SCALE]."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0 <= value <= MAX_NOISE_SCALE:
        raise InputError(f"{name} must be a number in [0, {MAX_NOISE_SCALE:g}] (a multiple of the rig's noise variances), got {value!r}")


@dataclass(frozen=True)
class Falloff:
    """Light falloff with distance d (metres) from a superpixel.

    ``inverse_square`` is the physical 1 / d^2. ``fitted`` is 1 / (a + b d^2) as fitted by a
    calibration; it can have a pole and change sign, so ``check`` must pass over the scene's
    distances before it is used.
    """

    kind: str = "inverse_square"
    a: float = 0.0
    b: float = 1.0

    def __post_init__(self):
        if self.kind not in ("inverse_square", "fitted"):
            raise InputError(f"falloff kind must be 'inverse_square' or 'fitted', got {self.kind!r}")
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in (self.a, self.b)):
            raise InputError(f"falloff a and b must be finite numbers, got {self.a!r}, {self.b!r}")

    def __call__(self, distance: torch.Tensor) -> torch.Tensor:
        """Falloff factor for distances ``distance`` (any shape, metres); same shape."""
        d2 = distance * distance
        if self.kind == "inverse_square":
            return 1.0 / d2
        return 1.0 / (self.a + self.b * d2)

    def check(self, distance: torch.Tensor) -> None:
        """Raise ``InputError`` unless the falloff is positive and finite at every distance given."""
        checked_falloff(self, distance.detach())

    def describe(self) -> str:
        """``falloff inverse_square`` or ``falloff fitted (a=.., b=..)``, for messages."""
        return f"falloff {self.kind}" + (f" (a={self.a:g}, b={self.b:g})" if self.kind == "fitted" else "")


def check_falloff(falloff) -> None:
    """Raise ``InputError`` unless ``falloff`` can be called with distances (a ``Falloff``, or any
    function of a tensor of metres): a solver would otherwise fail deep inside with a TypeError."""
    if not callable(falloff):
        raise InputError(f"falloff must be a function of distance in metres (e.g. capture_sim.rig.Falloff()), got {falloff!r}")


def falloff_at(falloff, distance: torch.Tensor) -> torch.Tensor:
    """``falloff(distance)`` as a tensor of ``distance``'s shape: a number (a constant falloff) is
    expanded, any other shape refused with ``InputError`` (a result that broadcast, (N, 1) for
    (N, K) distances, would weight every light alike). Values are not checked."""
    values = torch.as_tensor(falloff(distance))
    if values.dim() == 0:
        return values.expand(distance.shape)
    if values.shape != distance.shape:
        raise InputError(f"falloff returned shape {tuple(values.shape)} for distances of shape {tuple(distance.shape)}; "
                         "it must map each distance to one factor")
    return values


def checked_falloff(falloff, distance: torch.Tensor) -> torch.Tensor:
    """The falloff factors at ``distance``, refused unless positive and finite (DESIGN section 3: a
    fitted falloff can be negative or infinite at distances its fit did not cover).

    Args:
        falloff: callable mapping distances (metres) to falloff factors (tensor, array or number),
            e.g. ``Falloff()``.
        distance: light distances in metres, any shape.

    Returns:
        Factors of ``distance``'s shape, in its dtype or float32 if narrower (1 / d^2 of a few
        millimetres overflows float16; callers narrow the checked values themselves).

    Raises:
        InputError: a factor is not positive and finite.
    """
    check_falloff(falloff)
    wide = distance.to(torch.promote_types(distance.dtype, torch.float32))
    values = falloff_at(falloff, wide).to(wide.dtype)
    if not bool(torch.isfinite(values).all()) or bool((values <= 0).any()):
        name = falloff.describe() if isinstance(falloff, Falloff) else "falloff"
        lo, hi = float(distance.min()), float(distance.max())
        raise InputError(f"{name} is not positive and finite over light distances {lo:.3f}..{hi:.3f} m")
    return values


GAMMA_RANGE = (0.1, 10.0)
"""Accepted display gammas. Real displays are near 2.2; a value far outside (22 for 2.2) darkens
every set value below 1 to nothing without failing anywhere downstream."""


MAX_BIT_DEPTH = 16
"""Sensor bits at most: the float32 captures hold every level of 16 bits exactly apart, but not
of 24 (2^24 - 1 levels are as fine as float32's spacing near 1, so neighbouring levels merged)."""


@dataclass(frozen=True, eq=False)
class Rig:
    """A display-camera rig (DESIGN sections 2 and 3).

    Attributes:
        name: preset name or file stem.
        light_positions: (R, C, 3) superpixel centres, metres, camera frame; row 0 at the top.
        backlight: (R, C) backlight B added to every set value before the gamma (all channels).
        camera: intrinsics and image size.
        gamma: display non-linearity: emitted = scale * (P + B) ** gamma.
        scale: global display scale s.
        falloff: distance falloff model.
        exposure: fixed exposure/gain e, or None for auto exposure (DESIGN section 3).
        noise: sensor noise model.
        bit_depth: sensor quantisation in bits, or None for no quantisation.
        working_distance: metres from the camera to the plane used when a scene has no depth.
        panel_pixels: native display resolution (height, width) in display pixels, for export;
            None when the rig file does not give it (export then refuses the rig).
    """

    name: str
    light_positions: np.ndarray
    backlight: np.ndarray
    camera: Camera
    gamma: float = 2.2
    scale: float = 1.0
    falloff: Falloff = field(default_factory=Falloff)
    exposure: float | None = None
    noise: NoiseModel = field(default_factory=NoiseModel)
    bit_depth: int | None = 12
    working_distance: float = 0.5
    panel_pixels: tuple[int, int] | None = None

    def __post_init__(self):
        positions = np.asarray(self.light_positions, dtype=np.float64)
        check_light_positions(f"rig {self.name}: light_positions", positions)
        backlight = np.asarray(self.backlight, dtype=np.float64)
        if backlight.ndim == 0:
            backlight = np.full(positions.shape[:2], float(backlight))
        check_array(f"rig {self.name}: backlight", backlight, positions.shape[:2], value_range=(0.0, 1.0))
        object.__setattr__(self, "light_positions", positions)
        object.__setattr__(self, "backlight", backlight)
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise InputError(f"rig {self.name}: display scale must be positive and finite, got {self.scale!r}")
        if not GAMMA_RANGE[0] <= self.gamma <= GAMMA_RANGE[1]:
            raise InputError(
                f"rig {self.name}: display gamma must lie in [{GAMMA_RANGE[0]:g}, {GAMMA_RANGE[1]:g}] "
                f"(displays: about 1.8 to 2.6), got {self.gamma!r}"
            )
        if self.exposure is not None and not (self.exposure > 0 and math.isfinite(self.exposure)):
            raise InputError(f"rig {self.name}: exposure must be positive or auto")
        if self.bit_depth is not None and not (isinstance(self.bit_depth, numbers.Integral) and not isinstance(self.bit_depth, bool) and 1 <= self.bit_depth <= MAX_BIT_DEPTH):
            raise InputError(f"rig {self.name}: bit_depth must be a whole number in 1..{MAX_BIT_DEPTH} or none, got {self.bit_depth!r}")
        if not (math.isfinite(self.working_distance) and self.working_distance > 0):
            raise InputError(f"rig {self.name}: working_distance must be a positive number of metres, got {self.working_distance!r}")
        if self.panel_pixels is not None:
            object.__setattr__(self, "panel_pixels", panel_size(self.panel_pixels, f"rig {self.name}: panel_pixels"))

    @property
    def rows(self) -> int:
        return self.light_positions.shape[0]

    @property
    def cols(self) -> int:
        return self.light_positions.shape[1]

    @property
    def num_lights(self) -> int:
        """K = R * C."""
        return self.rows * self.cols

    def lights(self, dtype=torch.float32) -> torch.Tensor:
        """(K, 3) superpixel positions in light order k = r * C + c, metres, camera frame."""
        return torch.as_tensor(self.light_positions.reshape(-1, 3), dtype=dtype)

    def backlight_flat(self, dtype=torch.float32) -> torch.Tensor:
        """(K,) backlight in light order."""
        return torch.as_tensor(self.backlight.reshape(-1), dtype=dtype)

    def replace(self, **changes) -> "Rig":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def with_resolution(self, height: int, width: int) -> "Rig":
        """The rig imaging at ``height`` x ``width``, intrinsics scaled to match."""
        return self.replace(camera=self.camera.resized(height, width))

    def check_lights(self, num_lights: int, what: str = "OLAT stack") -> None:
        """Raise ``InputError`` if ``num_lights`` differs from this rig's R * C."""
        if num_lights != self.num_lights:
            raise InputError(
                f"{what} has {num_lights} lights but rig {self.name} has {self.rows} x {self.cols} = "
                f"{self.num_lights} superpixels"
            )


def available_rigs() -> list[str]:
    """Names of the rig presets in ``configs/rigs``."""
    return sorted(p.stem for p in RIG_DIR.glob("*.toml"))


def load_rig(name_or_path: str | Path = DEFAULT_RIG) -> Rig:
    """Load a rig from a preset name (``configs/rigs/NAME.toml``) or a TOML file path."""
    path = rig_source(name_or_path)
    try:
        return rig_from_dict(load_toml(path), default_name=path.stem)
    except InputError as err:  # messages name the rig by its `name`, which a copied file keeps
        if str(path) in str(err) or path.name in str(err):
            raise
        raise InputError(f"{err} (rig file {path})") from None


def rig_source(name_or_path: str | Path) -> Path:
    """The TOML file ``load_rig`` reads for a preset name or a file path (a preset's own file in
    ``configs/rigs``): what a run made with the rig depends on.

    Raises:
        InputError: an unknown preset, or a path that is not named *.toml.
    """
    path = Path(name_or_path)
    if path.suffix != ".toml":
        if path.exists() and not (RIG_DIR / f"{name_or_path}.toml").exists():
            raise InputError(f"rig {name_or_path}: a rig file must be a TOML file named *.toml (or give a preset: {', '.join(available_rigs())})")
        path = RIG_DIR / f"{name_or_path}.toml"
        if not path.exists():
            raise InputError(f"unknown rig {name_or_path!r}; presets: {', '.join(available_rigs())}")
    elif not path.exists():  # say that it is the rig, and where it was looked for
        raise InputError(f"rig file not found: {path.absolute()}")
    return path


def rig_file(name_or_path: str | Path) -> Path | None:
    """The user's TOML file a rig setting names (an input file that outputs must not replace), or
    None for a preset name (``load_rig``'s rule: a path ending in .toml is a file)."""
    return Path(name_or_path) if Path(name_or_path).suffix == ".toml" else None


RIG_KEYS = {
    "": ("name", "exposure", "bit_depth", "working_distance", "camera", "display", "noise", "falloff"),
    "camera": ("height", "width", "fx", "fy", "cx", "cy", "exposure_ms"),
    "display": ("gamma", "scale", "backlight", "panel_pixels", "light_positions", "panel"),
    "display.panel": ("rows", "cols", "diagonal_inch", "aspect", "curvature_radius", "distance", "offset", "tilt_deg"),
    "noise": ("shot", "read_std"),
    "falloff": ("kind", "a", "b"),
}
"""Keys of a rig TOML by table. A misspelt key would otherwise fall back to its default silently."""


def _boolean_key(value, where: str = "") -> tuple[str, bool] | None:
    """(dotted key, value) of the first boolean in a parsed TOML value, or None (``True == 1``:
    numpy and arithmetic take a boolean for a number silently, and no rig value is a boolean)."""
    if isinstance(value, bool):
        return where, value
    if isinstance(value, dict):
        children = [(f"{where}.{key}" if where else str(key), item) for key, item in value.items()]
    elif isinstance(value, list):
        children = [(where, item) for item in value]
    else:
        return None
    return next((found for key, item in children if (found := _boolean_key(item, key)) is not None), None)


def _check_rig_keys(config: dict, name: str) -> None:
    for table, known in RIG_KEYS.items():
        values = config
        for part in table.split(".") if table else ():
            values = values.get(part, {})
            if not isinstance(values, dict):
                raise InputError(f"rig {name}: [{table}] must be a table")
        unknown = sorted(set(values) - set(known))
        if unknown:
            where = f"[{table}]" if table else "top level"
            raise InputError(f"rig {name}: unknown key(s) {', '.join(unknown)} at {where}; known: {', '.join(known)}")
    boolean = _boolean_key(config)
    if boolean is not None:
        raise InputError(f"rig {name}: {boolean[0]} must hold numbers or text, got {boolean[1]!r}")
    falloff = config.get("falloff", {})
    # a and b belong to the fitted kind alone: missing, they would fall back to 1 / d^2 silently.
    if falloff.get("kind", "inverse_square") == "fitted" and not {"a", "b"} <= set(falloff):
        raise InputError(f"rig {name}: [falloff] kind = \"fitted\" needs both a and b (1 / (a + b d^2))")
    if falloff.get("kind", "inverse_square") == "inverse_square" and {"a", "b"} & set(falloff):
        raise InputError(f"rig {name}: [falloff] a and b apply to kind = \"fitted\" only; this falloff is inverse_square")


def rig_from_dict(config: dict, default_name: str = "rig") -> Rig:
    """Build a rig from the parsed TOML layout documented in ``configs/rigs/README.md``; unknown
    keys are errors."""
    _check_rig_keys(config, default_name)
    try:
        focal = {key: _number(f"camera {key}", config["camera"][key]) for key in ("fx", "fy", "cx", "cy")}
        camera = Camera(
            K_cam=_as_nested(np.array([[focal["fx"], 0.0, focal["cx"]], [0.0, focal["fy"], focal["cy"]], [0.0, 0.0, 1.0]])),
            height=_whole_number("camera height", config["camera"]["height"]),
            width=_whole_number("camera width", config["camera"]["width"]),
            exposure_ms=config["camera"].get("exposure_ms"),
        )
        display = config["display"]
        if "light_positions" in display and "panel" in display:  # one would be ignored without a word
            raise InputError(f"rig {default_name}: [display] gives both light_positions and a [display.panel] table; keep one")
        if "light_positions" in display:
            positions = _numbers("display light_positions", display["light_positions"])
        else:
            panel = _panel_settings(display)
            positions = panel_positions(**panel)  # validates the table, aspect included
            if "aspect" in display["panel"]:
                _warn_aspect_mismatch(panel, display.get("panel_pixels"), default_name)
        exposure = config.get("exposure", "auto")
        bit_depth = config.get("bit_depth", 12)
        return Rig(
            name=_text("name", config.get("name", default_name)),
            light_positions=positions,
            backlight=_numbers("display backlight", display.get("backlight", 0.0)),
            camera=camera,
            gamma=_number("display gamma", display.get("gamma", 2.2)),
            scale=_number("display scale", display.get("scale", 1.0)),
            falloff=Falloff(**config.get("falloff", {})),
            exposure=None if exposure == "auto" else _number("exposure", exposure, "a number or 'auto'"),
            noise=NoiseModel(**config.get("noise", {})),
            # ``False == 0``: a bool must not switch quantisation off.
            bit_depth=None if (bit_depth in (0, "none") and not isinstance(bit_depth, bool)) else _whole_number("bit_depth", bit_depth),
            working_distance=_number("working_distance", config.get("working_distance", 0.5)),
            panel_pixels=display.get("panel_pixels"),
        )
    except InputError as err:  # a check of a part (camera, panel, Rig): prefix the rig once
        message = str(err)
        raise InputError(message if message.startswith("rig ") else f"rig {default_name}: {message}") from None
    except KeyError as missing:
        raise InputError(f"rig {default_name}: missing key {missing}") from None
    except (TypeError, ValueError, OverflowError, ZeroDivisionError, IndexError) as err:
        # Values of the wrong kind or size: a list where a number goes, inf where a whole number
        # goes, a zero aspect ratio, a one-element offset.
        raise InputError(f"rig {default_name}: {err or type(err).__name__}") from None


def _panel_settings(display: dict) -> dict:
    """The ``[display.panel]`` table with its aspect ratio from ``panel_pixels`` (square display
    pixels) when it gives none."""
    panel = dict(display["panel"])
    if "aspect" not in panel and display.get("panel_pixels") is not None:
        height, width = panel_size(display["panel_pixels"], "display panel_pixels")
        panel["aspect"] = (float(width), float(height))
    return panel


def _warn_aspect_mismatch(panel: dict, panel_pixels, rig_name: str) -> None:
    """Warn when a stated (already validated) aspect differs from ``panel_pixels``' by over 1%:
    the superpixel positions follow the aspect, the exported frames the pixels."""
    if panel_pixels is None:
        return
    height, width = panel_size(panel_pixels, "display panel_pixels")
    aspect_width, aspect_height = panel["aspect"]
    if abs((aspect_width / aspect_height) / (width / height) - 1) > 0.01:
        warn_once(f"rig {rig_name}: [display.panel] aspect {aspect_width:g}:{aspect_height:g} differs from panel_pixels "
                  f"{width} x {height}; the superpixel positions follow the aspect, the exported frames the pixels",
                  stacklevel=4)  # the caller of load_rig


MAX_PANEL_SIDE = 65535
"""Largest display side in pixels (16K panels have 15360; a frame that size is already 12 GB)."""


def panel_size(panel_pixels, name: str = "panel_pixels") -> tuple[int, int]:
    """(height, width) of a display in pixels; ``InputError`` unless two whole numbers in
    1..MAX_PANEL_SIDE."""
    values = list(panel_pixels) if isinstance(panel_pixels, (list, tuple, np.ndarray)) else []
    if len(values) != 2 or not all(is_whole_number(v, 1) and v <= MAX_PANEL_SIDE for v in values):
        raise InputError(f"{name} must be two whole numbers in 1..{MAX_PANEL_SIDE} (height, width), got {panel_pixels!r}")
    return int(values[0]), int(values[1])


def camera_exposure_ms(value) -> float:
    """A rig's ``camera.exposure_ms`` (exposure time of one all-white capture) as a positive finite float."""
    expected = "a positive number of milliseconds"
    exposure_ms = _number("camera exposure_ms", value, expected)
    if not (math.isfinite(exposure_ms) and exposure_ms > 0):
        raise InputError(f"camera exposure_ms must be {expected}, got {value!r}")
    return exposure_ms


def _number(name: str, value, expected: str = "a number") -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{name} must be {expected}, got {value!r}")
    return float(value)


def _numbers(name: str, value) -> np.ndarray:
    """A number or nested list of numbers as a float64 array (TOML strings and booleans refused:
    numpy would convert "1.5" and true silently)."""
    try:
        array = np.asarray(value)
    except ValueError:  # a ragged nested list: numpy's message names no setting
        raise InputError(f"{name} must be a list of equal-length lists of numbers, got {one_line(repr(value))[:80]}") from None
    if array.dtype.kind not in "iuf":
        raise InputError(f"{name} must be numbers, got {one_line(repr(value))[:80]}")
    return array.astype(np.float64)


def _text(name: str, value) -> str:
    if not (isinstance(value, str) and value.strip()):
        raise InputError(f"{name} must be non-empty text, got {value!r}")
    return value


def _whole_number(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value):
        raise InputError(f"{name} must be a whole number, got {value!r}")
    return int(value)


def panel_positions(
    rows: int,
    cols: int,
    diagonal_inch: float = 55.0,
    aspect: tuple[float, float] = (16.0, 9.0),
    curvature_radius: float | None = None,
    distance: float = 0.0,
    offset: tuple[float, float] = (0.0, 0.0),
    tilt_deg: float = 0.0,
) -> np.ndarray:
    """Superpixel centres of a flat or curved panel facing the scene.

    The panel's centre sits at (offset_x, offset_y, -distance) in the camera frame and faces +z
    (towards the object). A curved panel bends about a vertical axis with radius
    ``curvature_radius`` (metres; None = flat), its edges closer to the object, as curved monitors
    do. ``tilt_deg`` rotates it about the x axis, positive bringing its top edge towards the object.

    Args:
        rows, cols: superpixel grid R x C over the whole panel.
        diagonal_inch: panel diagonal in inches.
        aspect: (width, height) aspect ratio.
        curvature_radius: radius of curvature in metres, at least width / pi; None or 0 for a flat panel.
        distance: metres the panel centre sits behind the camera centre (along -z).
        offset: (x, y) metres of the panel centre from the camera's optical axis.
        tilt_deg: tilt about the x axis in degrees.

    Returns:
        (R, C, 3) float64 positions in metres, camera frame.
    """
    def finite(value) -> bool:  # a real number (not a boolean, text or list)
        return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)

    def pair(value) -> bool:
        return isinstance(value, (list, tuple, np.ndarray)) and len(value) == 2 and all(finite(v) for v in value)

    if not (is_whole_number(rows, 1) and is_whole_number(cols, 1)):
        raise InputError(f"panel grid must be whole numbers of at least 1 x 1, got {rows!r} x {cols!r}")
    if not (pair(aspect) and all(side > 0 for side in aspect)):
        raise InputError(f"panel aspect must be two positive numbers (width, height), got {aspect!r}")
    if not pair(offset):
        raise InputError(f"panel offset must be two numbers (x, y) in metres, got {offset!r}")
    if not (finite(diagonal_inch) and diagonal_inch > 0):
        raise InputError(f"panel diagonal_inch must be positive, got {diagonal_inch!r}")
    if not finite(distance):
        raise InputError(f"panel distance must be a number of metres, got {distance!r}")
    if not (finite(tilt_deg) and abs(tilt_deg) <= 90):
        raise InputError(f"panel tilt_deg must be a number of degrees in [-90, 90], got {tilt_deg!r}")
    if not (curvature_radius is None or finite(curvature_radius)):
        raise InputError(f"panel curvature_radius must be a number of metres (0 or absent for a flat panel), got {curvature_radius!r}")
    diagonal = diagonal_inch * 0.0254
    aw, ah = aspect
    width, height = diagonal * aw / math.hypot(aw, ah), diagonal * ah / math.hypot(aw, ah)
    u = (np.arange(cols) + 0.5) / cols * width - width / 2  # arc length along the panel, metres
    v = (np.arange(rows) + 0.5) / rows * height - height / 2  # y down: row 0 at the top (negative y)
    uu, vv = np.meshgrid(u, v)
    # Beyond a half cylinder (arc angle above 90 degrees each side) the edges would turn back
    # towards the optical axis: no monitor is curved so, and such a number is a unit or typing mistake.
    if curvature_radius and not (math.isfinite(curvature_radius) and curvature_radius >= width / math.pi):
        raise InputError(f"panel curvature_radius must be at least the panel width / pi = {width / math.pi:.3g} m "
                         f"(0 or absent for a flat panel), got {curvature_radius!r}")
    if curvature_radius:
        theta = uu / curvature_radius
        x = curvature_radius * np.sin(theta)
        z = curvature_radius * (1 - np.cos(theta))
    else:
        x, z = uu, np.zeros_like(uu)
    y = vv
    tilt = math.radians(tilt_deg)
    # Rotate about x so that the top edge (negative y) moves towards +z.
    y_t = y * math.cos(tilt) + z * math.sin(tilt)
    z_t = -y * math.sin(tilt) + z * math.cos(tilt)
    return np.stack([x + offset[0], y_t + offset[1], z_t - distance], axis=-1)


def _as_nested(matrix: np.ndarray) -> tuple[tuple[float, float, float], ...]:
    return tuple(tuple(float(v) for v in row) for row in matrix)
