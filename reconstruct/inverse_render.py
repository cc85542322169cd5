"""Baseline inverse renderer: normals and J basis Cook-Torrance BRDFs from captures (DESIGN section 4).

The forward model, its image formula and its fast shading are in ``reconstruct.basis_render``; the
starting point (steps 1 to 3 below) in ``reconstruct.fit_start``.

Fit (Choi et al., ICCV 2025), with the changes marked (*):
1. Start: analytic photometric stereo (``solve_ps``; for OLAT captures a near-field Woodham least
   squares with reweighting against highlights, ``olat_least_squares``). (*) Pixels photometric
   stereo leaves invalid take their valid neighbours' values instead of facing the camera, and
   every normal is tilted to n . v >= 0.2: a start at n . v <= 0 sees no specular lobe, hence no
   gradient to leave by.
2. Clusters: k-means on hue and saturation of the photometric-stereo albedo (a pseudo-diffuse
   image) into J clusters: one-hot weights (softmax logits, 0.9 on the own cluster). (*) The
   tightest of 8 seeded k-means++ runs is kept: a single run can split one material and merge two.
3. Basis BRDFs: roughness 0.5. (*) Diffuse and specular albedos from their least-squares values at
   the starting normals and clusters (``least_squares_albedos``) instead of the cluster median and
   rho_s = 0.5: 0.5 in a scene's arbitrary radiometric units can be far off, and a lobe the scene
   does not have then dominates a short fit.
4. Adam on random batches of pixels, minimising
       RMSE(rendered - captured) + lambda_tv * TV(normals)
   with TV the mean L1 difference of unit normals between right and lower neighbours in the image
   grid. Saturated captures only say "at least full scale": their residual counts only where the
   rendering is darker. Learning rates decay exponentially.
5. (*) Normal search: with few patterns and sharp lobes, a pixel's error has local minima in the
   normal that gradient steps cannot leave (a start 15 degrees off stays there even with the true
   BRDFs). At a few points of the fit, the worst-fitted pixels try a grid over the visible
   hemisphere and a finer cap around the best (``search_normals``); the best candidate wins.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import torch

from capture_sim.errors import InputError, check_array, check_field_types, is_whole_number
from reconstruct.basis_render import NORM_FLOOR, RENDER_CHUNK_PIXELS, EmissionPlan, ShadingGeometry, render_under_patterns, shade_and_contract, shading_geometry
from reconstruct.fit_start import InitialEstimate, cluster_albedo, grid_neighbours, initial_estimate, least_squares_albedos



# ----------------------------------------------------------------------------------------------
# Settings
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FitConfig:
    """Settings of one inverse-rendering fit (``fit_inverse_render``)."""

    num_basis: int = 3
    """J, the number of basis BRDFs."""
    specular: bool = True
    """Fit GGX specular lobes; False fits Lambertian bases only (rho_s = 0, no lobe evaluated)."""
    iterations: int = 400
    """Adam steps."""
    batch_pixels: int = 8192
    """Pixels per step (random batches drawn without replacement from a shuffled order, reshuffled
    when fewer than a batch remain, so up to batch_pixels - 1 pixels sit out an epoch); all when fewer."""
    normal_lr: float = 0.03
    """Adam learning rate of the unnormalised normal vectors (unit length at the start)."""
    weight_lr: float = 0.1
    """Adam learning rate of the weight logits (weights = softmax of logits)."""
    brdf_lr: float = 0.03
    """Adam learning rate of the log diffuse albedos and the roughness logits."""
    specular_lr: float = 0.1
    """Adam learning rate of the log specular albedos: high enough that a lobe the scene does not
    have can fade by orders of magnitude within a short fit (rho_s starts at its least-squares
    value with ``least_squares_init``, else at 0.5)."""
    final_lr_fraction: float = 0.05
    """Learning rates decay exponentially to this fraction of their start by the last step."""
    tv_weight: float = 1e-3
    """lambda_tv: weight of the normals' total variation (mean L1 difference between neighbours)
    relative to the RMSE in full-scale units."""
    far_field: bool = False
    """Shade with the centroid's light directions and distances (see ``reconstruct.basis_render``)."""
    initial_specular: float = 0.5
    """Starting rho_s of every basis when ``least_squares_init`` is off, in the fit's albedo units
    (the scene's, or scaled to order one by ``albedo_unit``)."""
    least_squares_init: bool = True
    """Start the basis albedos (rho_d and rho_s) from their least-squares values at the initial
    normals, clusters and roughness (``least_squares_albedos``) instead of the cluster medians and
    0.5. A deliberate change from the published initialisation: 0.5 in a scene's arbitrary
    radiometric units can be far off (on a matte scene it starts the fit with a lobe 50 times the
    data's error), and a lobe the scene lacks then takes most of a short fit to fade."""
    specular_floor: float = 0.1
    """Least-squares rho_s start no lower than this fraction of ``initial_specular``. Some pattern
    sets leave the specular images nearly unconstrained at the initial normals, and least squares
    then gives rho_s ~ 0: started there, the fit brightened a diffuse albedo to take the highlights
    and stayed in that minimum (held-out PSNR ~27 dB instead of ~35 with some learned M = 4 sets;
    1e-3 was the previous value)."""
    initial_roughness: float = 0.5
    """Starting perceptual roughness of every basis."""
    min_roughness: float = 0.05
    """Lower bound of the roughness parameterisation r = r_min + (1 - r_min) sigmoid(theta)."""
    initial_weight: float = 0.9
    """Starting weight of a pixel's own cluster (the rest shared by the other bases); softmax weights
    cannot be exactly one-hot, and a softer start lets pixels change cluster."""
    normal_search_at: tuple[float, ...] = (0.0, 0.2, 0.4, 0.6)
    """Fractions of the fit at which badly fitted pixels search their normal globally
    (``search_normals``); empty for none. With few patterns and sharp lobes a pixel's error has
    local minima that Adam cannot leave (a start 15 degrees off can be stuck there)."""
    search_residual_ratio: float = 2.0
    """A pixel searches when its RMSE exceeds this many times the median pixel RMSE."""
    search_max_fraction: float = 0.1
    """At most this fraction of the pixels (the worst fitted) searches per round, to bound its cost."""
    search_candidates: int = 128
    """Normals of the coarse search grid over the visible hemisphere (about 13 degrees apart);
    the best is refined by a quarter as many within ``search_refine_deg``."""
    search_refine_deg: float = 10.0
    """Half-angle of the refinement cap around the best coarse normal, degrees."""
    saturation_threshold: float = 0.999
    """Captures at or above this count as saturated (only a lower bound on the rendering)."""
    seed: int = 0
    """Seed of k-means and of the pixel batches."""

    def __post_init__(self):
        check_field_types(self)  # whole numbers where ints go, and no NaN, which every comparison below lets through
        if self.num_basis < 1:
            raise InputError(f"num_basis must be at least 1, got {self.num_basis}")
        if self.iterations < 0 or self.batch_pixels < 1:
            raise InputError("iterations must be >= 0 and batch_pixels >= 1")
        if not all(0 < value < math.inf for value in (self.normal_lr, self.weight_lr, self.brdf_lr, self.specular_lr, self.initial_specular)):
            raise InputError("learning rates and initial_specular must be positive and finite")
        if not 0 < self.final_lr_fraction <= 1:
            raise InputError(f"final_lr_fraction must be in (0, 1], got {self.final_lr_fraction}")
        if not 0 <= self.tv_weight < math.inf:
            raise InputError(f"tv_weight must be non-negative and finite, got {self.tv_weight}")
        if not 0 <= self.specular_floor <= 1:
            raise InputError(f"specular_floor must be in [0, 1] (a fraction of initial_specular), got {self.specular_floor}")
        if not 0 < self.saturation_threshold <= 1:
            raise InputError(f"saturation_threshold must be in (0, 1], got {self.saturation_threshold}")
        if not 0 < self.min_roughness < self.initial_roughness < 1:
            raise InputError("need 0 < min_roughness < initial_roughness < 1")
        if not all(0 <= at < 1 for at in self.normal_search_at):
            raise InputError("normal_search_at fractions must lie in [0, 1)")
        if not 0 < self.search_max_fraction <= 1:
            raise InputError(f"search_max_fraction must be in (0, 1], got {self.search_max_fraction}")
        if self.search_candidates < 4 or not 0 < self.search_residual_ratio < math.inf or not 0 < self.search_refine_deg < 90:
            raise InputError("search_candidates >= 4, a finite search_residual_ratio > 0 and 0 < search_refine_deg < 90 needed")
        if not 0 < self.initial_weight < 1:
            raise InputError(f"initial_weight must be in (0, 1), got {self.initial_weight}")


class BasisModel(torch.nn.Module):
    """Unconstrained parameters of normals, simplex weights and J basis BRDFs.

    normals = raw / |raw|; weights = softmax(logits); rho_d = exp(log_diffuse); rho_s =
    exp(log_specular) (absent for Lambertian bases); r = r_min + (1 - r_min) sigmoid(theta).
    """

    def __init__(self, normal, labels, centres, config: FitConfig, specular_init: torch.Tensor | None = None):
        super().__init__()
        count, num_basis = normal.shape[0], config.num_basis
        self.min_roughness = config.min_roughness
        self.normal_raw = torch.nn.Parameter(normal.detach().float().clone())
        # Logit L for the own cluster so that its softmax weight is initial_weight.
        own = math.log(config.initial_weight * max(num_basis - 1, 1) / (1.0 - config.initial_weight)) if num_basis > 1 else 0.0
        logits = torch.zeros((count, num_basis))
        logits[torch.arange(count), labels] = own
        self.weight_logits = torch.nn.Parameter(logits)
        self.log_diffuse = torch.nn.Parameter(centres.detach().float().clamp_min(1e-4).log())
        if specular_init is None:
            specular_init = torch.full((num_basis,), config.initial_specular)
        floor = config.initial_specular * config.specular_floor
        self.log_specular = torch.nn.Parameter(specular_init.float().clamp_min(floor).log()) if config.specular else None
        fraction = (config.initial_roughness - config.min_roughness) / (1.0 - config.min_roughness)
        self.roughness_logit = torch.nn.Parameter(torch.full((num_basis,), math.log(fraction / (1.0 - fraction))))

    @classmethod
    def from_result(cls, result: "InverseRenderResult", config: FitConfig) -> "BasisModel":
        """A model whose parameters reproduce ``result`` (weights floored at 1e-6 before the log)."""
        count = result.normal.shape[0]
        model = cls(result.normal, torch.zeros(count, dtype=torch.int64), result.diffuse.clamp_min(1e-4), config,
                    result.specular if result.specular_enabled else None)
        with torch.no_grad():
            model.weight_logits.copy_(result.weights.float().clamp_min(1e-6).log())
            if model.log_specular is not None:
                model.log_specular.copy_(result.specular.float().clamp_min(1e-8).log())
            fraction = ((result.roughness.float() - config.min_roughness) / (1.0 - config.min_roughness)).clamp(1e-4, 1 - 1e-4)
            model.roughness_logit.copy_(torch.log(fraction / (1.0 - fraction)))
        return model

    def normals(self, index=None) -> torch.Tensor:
        """(N or n, 3) unit normals, camera frame, of every pixel or of pixels ``index``."""
        raw = self.normal_raw if index is None else self.normal_raw[index]
        return raw / raw.norm(dim=-1, keepdim=True).clamp_min(NORM_FLOOR)

    def weights(self, index=None) -> torch.Tensor:
        """(N or n, J) basis weights (softmax: non-negative, summing to 1 per pixel)."""
        logits = self.weight_logits if index is None else self.weight_logits[index]
        return torch.softmax(logits, dim=-1)

    def diffuse(self) -> torch.Tensor:
        """(J, 3) diffuse albedo per basis BRDF, in the fit's albedo units (``albedo_unit``)."""
        return self.log_diffuse.exp()

    def specular(self) -> torch.Tensor | None:
        """(J,) specular albedo per basis BRDF (grey: one value for all channels) in the same units, or
        None (Lambertian fit)."""
        return None if self.log_specular is None else self.log_specular.exp()

    def roughness(self) -> torch.Tensor:
        """(J,) GGX roughness per basis BRDF, in [min_roughness, 1] (dimensionless)."""
        return self.min_roughness + (1.0 - self.min_roughness) * torch.sigmoid(self.roughness_logit)


@dataclass(frozen=True, eq=False)
class InverseRenderResult:
    """A fitted basis-BRDF scene (float32, detached).

    Attributes:
        normal: (N, 3) unit normals, camera frame.
        weights: (N, J) basis weights on the simplex.
        diffuse: (J, 3) basis diffuse albedos rho_d (scene radiometric units; pi times the
            photometric-stereo albedo ``PSResult.albedo``, which absorbs the Lambertian 1 / pi).
        specular: (J,) basis specular albedos rho_s (zeros for a Lambertian model).
        roughness: (J,) basis perceptual roughness.
        specular_enabled: False for a Lambertian model (no lobes are rendered).
        far_field: the model was fitted with far-field shading.
        loss_history: per-step total loss.
        rmse_history: per-step RMSE data term (full scale 1).
        seconds: wall time of the optimisation (without the initial estimate), setup included.
        setup_seconds: the part of ``seconds`` before the first step (clusters, least-squares
            albedos, shading constants).
        normals_searched: pixels whose normal the global search changed (all rounds).
    """

    normal: torch.Tensor
    weights: torch.Tensor
    diffuse: torch.Tensor
    specular: torch.Tensor
    roughness: torch.Tensor
    specular_enabled: bool
    far_field: bool
    loss_history: list = field(default_factory=list)
    rmse_history: list = field(default_factory=list)
    seconds: float = 0.0
    setup_seconds: float = 0.0
    normals_searched: int = 0

    @property
    def num_basis(self) -> int:
        return int(self.diffuse.shape[0])

    def render(self, points, lights, emission, falloff, chunk_pixels: int = RENDER_CHUNK_PIXELS) -> torch.Tensor:
        """(M, N, 3) noise-free, unclipped images of the fitted scene under ``emission`` (M, K, 3)."""
        with torch.no_grad():
            return render_under_patterns(
                self.normal, points.float(), lights.float(), emission.float(), self.weights, self.diffuse,
                self.specular if self.specular_enabled else None, self.roughness, falloff, self.far_field, chunk_pixels,
            )

    def describe(self) -> dict:
        """JSON-ready basis BRDF parameters."""
        return {
            "J": self.num_basis,
            "specular": self.specular_enabled,
            "far_field": self.far_field,
            "diffuse_albedo": self.diffuse.tolist(),
            "specular_albedo": self.specular.tolist(),
            "roughness": self.roughness.tolist(),
        }


# ----------------------------------------------------------------------------------------------
# Fit
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class FitProblem:
    """What a fit is fitted to: captures under known emission, and the geometry they were taken of.

    One object serves the final fit, every candidate of model selection and its scoring, so the
    eight inputs travel together instead of being repeated through every signature.

    Attributes:
        captures: (M, N, 3) captures of the masked pixels in [0, 1] (1 = saturated).
        emission: (M, K, 3) effective emission (see ``fit_inverse_render``).
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: distance falloff (positive and finite over the scene).
        pixel_index: (N,) flat indices of the pixels in the H x W image.
        height, width: image size.
    """

    captures: torch.Tensor
    emission: torch.Tensor
    points: torch.Tensor
    lights: torch.Tensor
    falloff: Callable
    pixel_index: torch.Tensor
    height: int
    width: int

    def with_patterns(self, index: torch.Tensor) -> "FitProblem":
        """The same scene with only the patterns (captures and emission rows) ``index``."""
        return FitProblem(self.captures[index], self.emission[index], self.points, self.lights, self.falloff,
                          self.pixel_index, self.height, self.width)

    def initial_estimate(self) -> "InitialEstimate":
        """``initial_estimate`` of these captures, with the image grid for filling invalid pixels."""
        return initial_estimate(self.captures, self.emission, self.points, self.lights, self.falloff,
                                pixel_index=self.pixel_index, height=self.height, width=self.width)

    def fit(self, config: "FitConfig" = None, initial: "InitialEstimate | None" = None, log=None,
            warm_start: "InverseRenderResult | None" = None) -> "InverseRenderResult":
        """``fit_inverse_render`` of this problem."""
        return fit_inverse_render(self.captures, self.emission, self.points, self.lights, self.falloff, self.pixel_index,
                                  self.height, self.width, FitConfig() if config is None else config, initial, log, warm_start)

    def relight(self, result: "InverseRenderResult", emission: torch.Tensor) -> torch.Tensor:
        """(V, N, 3) noise-free, unclipped images of a fitted ``result`` under other ``emission`` (V, K, 3)."""
        return result.render(self.points, self.lights, emission, self.falloff)


def capture_residual(rendered: torch.Tensor, captures: torch.Tensor, saturated: torch.Tensor) -> torch.Tensor:
    """Rendered minus captured, except that a saturated capture only penalises a darker rendering.

    Args:
        rendered, captures: linear images of one layout, e.g. (N, M, 3) or (M, N, 3), full scale 1.
        saturated: bool, the same shape: the capture reached the saturation threshold.

    Returns:
        The residual, the same shape.
    """
    residual = rendered - captures
    return torch.where(saturated, residual.clamp_max(0.0), residual)


def _check_fit_inputs(captures, emission, points, lights, pixel_index, height, width):
    check_array("captures", captures, ("M", "N", 3))
    check_array("emission", emission, (captures.shape[0], "K", 3), value_range=(0.0, math.inf))
    check_array("points", points, (captures.shape[1], 3))
    check_array("lights", lights, (emission.shape[1], 3))
    check_array("pixel_index", pixel_index, (captures.shape[1],))
    if captures.shape[1] == 0:
        raise InputError("captures hold no pixels")
    if captures.shape[0] == 0 or not bool((torch.as_tensor(emission) > 0).any()):
        raise InputError("the inverse renderer needs at least one pattern with some emitted light")
    if not all(isinstance(value, torch.Tensor) for value in (captures, emission, points, lights, pixel_index)):
        raise InputError("captures, emission, points, lights and pixel_index must be torch tensors")
    if not (captures.is_floating_point() and emission.is_floating_point()):
        raise InputError("captures and emission must be floating-point torch tensors")
    if not (is_whole_number(height, 1) and is_whole_number(width, 1)):
        raise InputError(f"height and width must be positive whole numbers, got {height!r} x {width!r}")
    index = torch.as_tensor(pixel_index)
    if index.is_floating_point() or index.dtype == torch.bool or index.unique().numel() != index.numel():
        raise InputError("pixel_index must hold distinct integer pixel indices")
    if int(pixel_index.min()) < 0 or int(pixel_index.max()) >= height * width:
        raise InputError(f"pixel_index must lie in [0, {height * width}) for a {height} x {width} image")


EMISSION_RANGE = (1e-30, 1e30)
"""Emission peaks the inverse renderer accepts (albedos scale inversely and must fit float32)."""
TYPICAL_ALBEDO = 0.5
"""The fit runs in albedo units where the 90th percentile albedo is near this."""


def fit_inverse_render(
    captures: torch.Tensor,
    emission: torch.Tensor,
    points: torch.Tensor,
    lights: torch.Tensor,
    falloff: Callable,
    pixel_index: torch.Tensor,
    height: int,
    width: int,
    config: FitConfig = FitConfig(),
    initial: InitialEstimate | None = None,
    log: Callable[[int, dict], None] | None = None,
    warm_start: InverseRenderResult | None = None,
) -> InverseRenderResult:
    """Recover normals, basis weights and J basis BRDFs from captures under known patterns.

    Args:
        captures: (M, N, 3) captures of the masked pixels in [0, 1] (1 = saturated).
        emission: (M, K, 3) effective emission E = exposure * scale * (P + B) ** gamma, so that
            noise-free I = sum_k E O; for an OLAT stack, exposure times one-hot rows. Any units
            with a peak in EMISSION_RANGE: the fit runs in albedo units scaled by a power of two
            (``albedo_unit``), so that its settings in albedo units (``initial_specular``, the
            floors) mean the same whatever the emission's units, and returns albedos in the
            caller's units.
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: distance falloff (positive and finite over the scene).
        pixel_index: (N,) flat indices of the pixels in the H x W image (for the TV neighbours).
        height, width: image size.
        config: fit settings.
        initial: the photometric-stereo starting point (computed here when None).
        log: optional callback ``log(step, scalars)`` called every 10 steps and at the end.
        warm_start: start from this result's parameters instead of the photometric-stereo and
            k-means initialisation (its J and specular setting must match ``config``).

    Returns:
        InverseRenderResult.

    Raises:
        InputError: wrong shapes, non-finite inputs, or an emission peak outside EMISSION_RANGE.
    """
    _check_fit_inputs(captures, emission, points, lights, pixel_index, height, width)
    points, lights = points.float(), lights.float()
    captures, emission = captures.detach().float(), emission.detach().float()
    peak = float(emission.amax())
    if not EMISSION_RANGE[0] <= peak <= EMISSION_RANGE[1]:
        raise InputError(f"emission peak {peak:.3g} lies outside [{EMISSION_RANGE[0]:g}, {EMISSION_RANGE[1]:g}], where "
                         "the inverse renderer's float32 albedos stay representable; rescale the emission")
    if warm_start is not None:
        if warm_start.num_basis != config.num_basis or warm_start.specular_enabled != config.specular:
            raise InputError("warm_start must have the same J and specular setting as the config")
        if warm_start.normal.shape[0] != captures.shape[1]:
            raise InputError("warm_start has a different number of pixels than the captures")
        unit = albedo_unit(torch.cat([warm_start.diffuse.flatten(), warm_start.specular.flatten()]))
    else:
        if initial is None:
            initial = initial_estimate(captures, emission, points, lights, falloff, pixel_index=pixel_index, height=height, width=width)
        unit = albedo_unit(initial.albedo[initial.valid].amax(-1) if bool(initial.valid.any()) else initial.albedo.amax(-1))
    # Fit in albedo units near one (the settings and floors are in such units), whatever the
    # emission's units; images are unchanged, the albedos are scaled back below.
    emission = emission * unit
    start = time.perf_counter()
    if warm_start is not None:
        model = BasisModel.from_result(scale_albedos(warm_start, 1.0 / unit), config)
    else:
        model = _initial_model(captures, emission, points, lights, falloff, dataclasses.replace(initial, albedo=initial.albedo / unit), config)
    result = _optimise(model, captures, emission, points, lights, falloff, pixel_index, height, width, config, log, start)
    return scale_albedos(result, unit)


def albedo_unit(albedo: torch.Tensor) -> float:
    """The power of two u that brings the 90th percentile of albedos (any shape) nearest to
    TYPICAL_ALBEDO: the fit runs on albedo / u and emission * u. Albedo is relative to the
    emission, so emission in other units (a raw exposure, another radiometric unit) shifts it by
    the same factor; in units of u the fit's settings in albedo units (``initial_specular``, the
    floors) mean the same for every scene. 1 for physical albedos of a typical bright object."""
    values = albedo.detach().double().flatten()
    values = values[torch.isfinite(values) & (values > 0)]
    if values.numel() == 0:
        return 1.0
    return 2.0 ** round(math.log2(float(values.quantile(0.9)) / TYPICAL_ALBEDO))


def scale_albedos(result: "InverseRenderResult", factor: float) -> "InverseRenderResult":
    """``result`` with its diffuse and specular albedos multiplied by ``factor``."""
    if factor == 1.0:
        return result
    return dataclasses.replace(result, diffuse=result.diffuse * factor, specular=result.specular * factor)


def _initial_model(captures, emission, points, lights, falloff, initial: InitialEstimate, config: FitConfig) -> "BasisModel":
    """k-means clusters and (least-squares) basis albedos at the photometric-stereo start."""
    labels, centres = cluster_albedo(initial.albedo, initial.valid, config.num_basis, config.seed)
    specular_init = None
    if config.least_squares_init:
        diffuse_ls, specular_ls, solved = least_squares_albedos(
            captures, emission, points, lights, falloff, initial.normal, labels, config.num_basis, config.specular,
            config.initial_roughness, config.saturation_threshold, seed=config.seed,
        )
        # The photometric-stereo albedo explains all reflected light as diffuse, so a cluster's
        # diffuse albedo should not exceed it. A least-squares value above it means the specular
        # images at the initial normals and roughness could not take the highlights (weakly
        # constrained by some pattern sets): starting there, the fit settled in a minimum with an
        # over-bright basis (held-out PSNR ~28 dB instead of ~36 with some learned M = 4 sets).
        centres = torch.where(solved[:, None], torch.minimum(diffuse_ls, centres), centres)
        specular_init = specular_ls if config.specular else None
    return BasisModel(initial.normal, labels, centres, config, specular_init)


def cap_directions(count: int, min_cosine: float) -> torch.Tensor:
    """(count, 3) unit vectors spread evenly (Fibonacci spiral) over the cap z >= min_cosine."""
    index = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - index / count * (1.0 - min_cosine)
    azimuth = index * math.pi * (3.0 - math.sqrt(5.0))
    radius = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    return torch.stack([radius * torch.cos(azimuth), radius * torch.sin(azimuth), z], dim=1).float()


def _frames(axis: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) orthonormal frames whose third row is the unit ``axis`` (B, 3)."""
    helper = torch.where(axis[:, :1].abs() < 0.9, torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
    first = torch.linalg.cross(helper.expand_as(axis), axis)
    first = first / first.norm(dim=-1, keepdim=True).clamp_min(NORM_FLOOR)
    return torch.stack([first, torch.linalg.cross(axis, first), axis], dim=1)


def _candidate_errors(candidates, index, geometry, plan, captures, saturated, weights, diffuse, specular, roughness):
    """Sum of squared residuals (B, C) of candidate unit normals (B, C, 3) of the pixels ``index``."""
    batch, count = candidates.shape[:2]
    repeated = index.repeat_interleave(count)
    rendered = shade_and_contract(candidates.reshape(-1, 3), geometry.take(repeated), plan,
                                  weights[repeated], diffuse, specular, roughness)  # (M, B * C, 3)
    rendered = rendered.reshape(rendered.shape[0], batch, count, 3).permute(1, 2, 0, 3)
    residual = capture_residual(rendered, captures[index][:, None], saturated[index][:, None])
    return residual.square().sum((2, 3))


def search_normals(model: "BasisModel", index: torch.Tensor, geometry: ShadingGeometry, plan: EmissionPlan,
                   pixels_first: torch.Tensor, saturated: torch.Tensor, config: FitConfig, min_cosine: float = 0.1,
                   work: int = 8192) -> torch.Tensor:
    """Global normal search for the pixels ``index`` at the model's current BRDFs and weights.

    Coarse: ``search_candidates`` normals over the visible hemisphere (n . v >= ``min_cosine``,
    in each pixel's view frame) plus the current normal; fine: a quarter as many within
    ``search_refine_deg`` of the best. The lowest sum of squared residuals wins, so no pixel
    gets worse. Changes ``model.normal_raw`` in place.

    Args:
        model: the fit's parameters (normals of all N pixels).
        index: (B,) long, the pixels to search.
        geometry, plan: shading geometry of all N pixels and the patterns' emission.
        pixels_first: (N, M, 3) captures, pixel-major.
        saturated: (N, M, 3) bool, saturated captures (``capture_residual``).
        config: search settings (``search_candidates``, ``search_refine_deg``).
        min_cosine: smallest n . v of a candidate.
        work: candidate renderings per batch (bounds the temporaries).

    Returns:
        (B,) bool, the pixels whose normal changed.
    """
    with torch.no_grad():
        weights, diffuse, specular, roughness = model.weights(), model.diffuse(), model.specular(), model.roughness()
        coarse = cap_directions(config.search_candidates, min_cosine)
        fine = cap_directions(max(config.search_candidates // 4, 4), math.cos(math.radians(config.search_refine_deg)))
        changed = torch.zeros(index.numel(), dtype=torch.bool)
        per_chunk = max(1, work // (config.search_candidates + 1))
        for start in range(0, index.numel(), per_chunk):
            chunk = index[start : start + per_chunk]
            current = model.normals(chunk)
            view = geometry.view if geometry.far_field else geometry.view[chunk]
            arguments = (chunk, geometry, plan, pixels_first, saturated, weights, diffuse, specular, roughness)
            best = current
            for directions, axis in ((coarse, view.expand_as(current)), (fine, None)):
                frame = _frames(best if axis is None else axis)
                candidates = torch.cat([best[:, None], torch.einsum("cd,bde->bce", directions, frame)], dim=1)
                errors = _candidate_errors(candidates, *arguments)
                best = candidates[torch.arange(chunk.numel()), errors.argmin(1)]
            moved = (best - current).norm(dim=-1) > 1e-6
            model.normal_raw[chunk[moved]] = best[moved]
            changed[start : start + chunk.numel()] = moved
    return changed


def pixel_rmse(model: "BasisModel", geometry: ShadingGeometry, plan: EmissionPlan, pixels_first, saturated, chunk_pixels: int = 4096) -> torch.Tensor:
    """(N,) RMSE of every pixel's rendering at the model's current parameters, in capture units.

    ``pixels_first`` (N, M, 3) are the captures, pixel-major, and ``saturated`` (N, M, 3) bool
    their saturated entries (``capture_residual``); pixels are rendered ``chunk_pixels`` at a time.
    """
    count = pixels_first.shape[0]
    errors = torch.empty(count)
    with torch.no_grad():
        weights, diffuse, specular, roughness = model.weights(), model.diffuse(), model.specular(), model.roughness()
        for start in range(0, count, chunk_pixels):
            index = torch.arange(start, min(start + chunk_pixels, count))
            rendered = shade_and_contract(model.normals(index), geometry.take(index), plan, weights[index], diffuse, specular, roughness)
            residual = capture_residual(rendered.permute(1, 0, 2), pixels_first[index], saturated[index])
            errors[index] = residual.square().mean((1, 2)).sqrt()
    return errors


def search_round(model: "BasisModel", geometry: ShadingGeometry, plan: EmissionPlan, pixels_first, saturated, config: FitConfig) -> torch.Tensor:
    """One round of normal search: pixels whose RMSE exceeds ``search_residual_ratio`` times the
    median (at most ``search_max_fraction`` of them, worst first) search their normal.
    ``pixels_first`` (N, M, 3) and ``saturated`` (N, M, 3) as in ``pixel_rmse``.

    Returns:
        (S,) long indices of the pixels whose normal changed.
    """
    errors = pixel_rmse(model, geometry, plan, pixels_first, saturated)
    stuck = torch.nonzero(errors > config.search_residual_ratio * errors.median()).squeeze(1)
    limit = max(1, int(config.search_max_fraction * errors.numel()))
    if stuck.numel() > limit:
        stuck = stuck[torch.topk(errors[stuck], limit).indices]
    if stuck.numel() == 0:
        return stuck
    return stuck[search_normals(model, stuck, geometry, plan, pixels_first, saturated, config)]


def _optimise(model, captures, emission, points, lights, falloff, pixel_index, height, width, config: FitConfig, log, start) -> InverseRenderResult:
    """Adam on random pixel batches: RMSE data term plus TV on the normals (module docstring)."""
    plan = EmissionPlan(emission)
    geometry = shading_geometry(points, lights[plan.light_index], falloff, far_field=config.far_field)
    pixels_first = captures.permute(1, 0, 2).contiguous()  # (N, M, 3): batches gather rows
    saturated_all = pixels_first >= config.saturation_threshold
    neighbours = grid_neighbours(pixel_index.long(), height, width)

    groups = [
        {"params": [model.normal_raw], "lr": config.normal_lr},
        {"params": [model.weight_logits], "lr": config.weight_lr},
        {"params": [model.log_diffuse, model.roughness_logit], "lr": config.brdf_lr},
    ]
    if model.log_specular is not None:
        groups.append({"params": [model.log_specular], "lr": config.specular_lr})
    optimiser = torch.optim.Adam(groups, fused=True)
    decay = config.final_lr_fraction ** (1.0 / max(config.iterations, 1))
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimiser, decay)
    generator = torch.Generator().manual_seed(config.seed)
    count = captures.shape[1]
    batch = min(config.batch_pixels, count)
    order = torch.randperm(count, generator=generator)
    cursor = 0
    loss_history, rmse_history = [], []
    search_steps = {int(round(at * config.iterations)) for at in config.normal_search_at}
    searched = 0
    setup_seconds = time.perf_counter() - start
    for step in range(config.iterations):
        # ---- global normal search for pixels stuck far above the typical error
        if step in search_steps:
            moved = search_round(model, geometry, plan, pixels_first, saturated_all, config)
            searched += int(moved.numel())
            if moved.numel():
                state = optimiser.state.get(model.normal_raw, {})
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in state:
                        state[key][moved] = 0.0  # stale momentum would pull the pixel back

        # ---- batch: the next slice of a random permutation, so every pixel is seen once per epoch
        if batch == count:
            index = None
        else:
            if cursor + batch > count:
                order, cursor = torch.randperm(count, generator=generator), 0
            index = order[cursor : cursor + batch]
            cursor += batch
        batch_geometry = geometry if index is None else geometry.take(index)
        batch_captures = pixels_first if index is None else pixels_first[index]
        batch_saturated = saturated_all if index is None else saturated_all[index]

        # ---- data term: RMSE of the rendered captures
        normal = model.normals(index)
        rendered = shade_and_contract(normal, batch_geometry, plan, model.weights(index), model.diffuse(), model.specular(), model.roughness())
        residual = capture_residual(rendered.permute(1, 0, 2), batch_captures, batch_saturated)
        rmse = torch.sqrt(residual.square().mean() + 1e-12)

        # ---- regulariser: total variation of the normals over right and lower neighbours
        loss = rmse
        if config.tv_weight > 0:
            pairs = neighbours if index is None else neighbours[index]
            present = pairs >= 0
            if bool(present.any()):
                neighbour_normals = model.normals(pairs.clamp_min(0).reshape(-1)).reshape(-1, 2, 3)
                difference = (normal[:, None, :] - neighbour_normals).abs().sum(-1)
                tv = (difference * present).sum() / present.sum()
                loss = loss + config.tv_weight * tv

        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        scheduler.step()
        loss_history.append(float(loss.detach()))
        rmse_history.append(float(rmse.detach()))
        if log is not None and (step % 10 == 0 or step == config.iterations - 1):
            scalars = {"loss/total": loss_history[-1], "loss/rmse": rmse_history[-1]}
            with torch.no_grad():
                for j, value in enumerate(model.roughness().tolist()):
                    scalars[f"basis_{j}/roughness"] = value
                for j, value in enumerate((model.specular() if config.specular else torch.zeros(config.num_basis)).tolist()):
                    scalars[f"basis_{j}/specular_albedo"] = value
                for j, value in enumerate(model.diffuse().mean(1).tolist()):
                    scalars[f"basis_{j}/diffuse_albedo_mean"] = value
            log(step, scalars)

    with torch.no_grad():
        specular = model.specular()
        return InverseRenderResult(
            normal=model.normals().detach().clone(),
            weights=model.weights().detach().clone(),
            diffuse=model.diffuse().detach().clone(),
            specular=specular.detach().clone() if specular is not None else torch.zeros(config.num_basis),
            roughness=model.roughness().detach().clone(),
            specular_enabled=config.specular,
            far_field=config.far_field,
            loss_history=loss_history,
            rmse_history=rmse_history,
            seconds=time.perf_counter() - start,
            setup_seconds=setup_seconds,
            normals_searched=searched,
        )
