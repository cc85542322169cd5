"""No more model than the scene needs: the number of basis BRDFs, specular or not, near or far field.

Basis and lobes. Candidates are (J, Lambertian) and (J, specular) for J = 1, 2, ... Each is fitted
briefly and scored by its relighting PSNR on validation lights (never the test lights, see
``reconstruct.relight``). The sweep over J stops early once the best PSNR has not improved by more
than ``min_improvement_db`` for ``patience`` consecutive J. The chosen model is the smallest one,
ordered by (J, specular), whose validation PSNR is within ``tolerance_db`` of the best candidate's:
    choose min (J, specular)  such that  PSNR(J, specular) >= max PSNR - tolerance_db
With tolerance_db = 0.5 dB, a bigger model must cut the relighting RMSE by more than about 6 %
(10^(-0.5/20) = 0.944) to be worth its parameters. PSNRs above ``psnr_ceiling_db`` (60 dB) count
as that ceiling in the rule and in the early stop: there, differences are the fits' convergence,
not the model (noise-free captures of a uniform Lambertian sphere scored 80.6 dB with J = 1 and
83.1 with J = 2, which a bare 0.5 dB rule took for a second material).

Light model. Near-field shading (per-pixel light directions and distances) is the truth of a
display rig, but when the display is far compared with the object it is indistinguishable from
far-field shading (one direction and distance per light). ``choose_light_model`` renders the
photometric-stereo starting point (normals and albedo) both ways under the fit emission and picks
far field only when they differ by less than ``far_field_tolerance`` in relative RMS,
    sqrt(mean((near - far)^2) / mean(near^2)) < 0.005,
a scale-free test (an absolute PSNR would call any dim, short-exposed capture "indistinguishable").
0.5 % is below the shot noise of a well-exposed capture (reference sensor: sqrt(1e-4 * 0.5) / 0.5
= 1.4 % at half scale); on the reference rig (object 0.5 m away, display 1.2 m wide) synthetic
spheres differ by 7-9 %. It also reports the spread of light directions and falloff across the object.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import torch

from capture_sim.errors import InputError, check_array, check_field_types
from capture_sim.geometry import light_geometry
from reconstruct.basis_render import render_under_patterns
from reconstruct.fit_start import InitialEstimate
from reconstruct.inverse_render import FitConfig, FitProblem
from reconstruct.relight import pooled_psnr


LOBE_CHOICES = (False, True)
"""The ``specular`` values tried for every J, smaller model first: Lambertian, then GGX lobes."""


@dataclass(frozen=True)
class SelectionConfig:
    """Settings of the model sweep (``select_model``) and of the light-model test."""

    max_basis: int = 8
    """Largest J tried."""
    tolerance_db: float = 0.5
    """The smallest model within this many dB of the best validation PSNR is chosen."""
    psnr_ceiling_db: float = 60.0
    """Validation PSNRs above this count as this in the choice and the early stop: a relighting RMSE
    of 0.1 % of full scale, which the shot noise of exposed captures keeps out of reach (the
    reference sensor's is 0.7 % at half scale; its noisy captures of a Lambertian sphere score
    about 45 dB), so reached only by noise-free captures, whose PSNRs differ by the fits'
    convergence (``inf`` compares every PSNR as it is)."""
    min_improvement_db: float = 0.1
    """A J counts as an improvement when it raises the best validation PSNR by more than this."""
    patience: int = 2
    """The J sweep stops after this many consecutive J without improvement."""
    iterations: int = 150
    """Adam steps per candidate fit (fewer than the final fit: candidates only need ranking)."""
    batch_pixels: int = 2048
    """Pixels per Adam step of a candidate (the final fit uses its own batch size)."""
    far_field_tolerance: float = 0.005
    """Far-field shading is used when its rendering of the starting point differs from near field's
    by less than this relative RMS."""

    def __post_init__(self):
        check_field_types(self)  # first: no NaN or text, which the comparisons below let through or fail on
        if self.max_basis < 1 or self.patience < 1 or self.iterations < 1 or self.batch_pixels < 1:
            raise InputError("SelectionConfig: max_basis, patience, iterations and batch_pixels must be >= 1")
        if not all(0 <= value < math.inf for value in (self.tolerance_db, self.min_improvement_db, self.far_field_tolerance)):
            raise InputError("SelectionConfig: tolerances must be non-negative and finite")
        if not self.psnr_ceiling_db > 0:
            raise InputError(f"SelectionConfig: psnr_ceiling_db must be positive (inf for none), got {self.psnr_ceiling_db!r}")

    @property
    def max_candidates(self) -> int:
        """Candidate fits of a sweep that does not stop early: a Lambertian and a specular one per J
        (``select_model``); the total of a progress display."""
        return len(LOBE_CHOICES) * self.max_basis


@dataclass(frozen=True)
class Candidate:
    """One fitted candidate model and its validation score.

    Attributes:
        num_basis: J.
        specular: GGX lobes fitted (False: Lambertian bases).
        psnr: validation relighting PSNR, dB.
        rmse: validation relighting RMSE, full-scale units.
        seconds: wall time of its fit and evaluation.
        details: anything else worth reporting (e.g. the test PSNR, for information only).
    """

    num_basis: int
    specular: bool
    psnr: float
    rmse: float
    seconds: float
    details: dict = field(default_factory=dict)

    @property
    def size(self) -> tuple[int, int]:
        """Order of model size: more bases first, then lobes."""
        return (self.num_basis, int(self.specular))


@dataclass(frozen=True)
class Selection:
    """Result of a model sweep.

    Attributes:
        chosen: the selected candidate.
        best: the candidate with the highest validation PSNR.
        curve: every candidate fitted, in the order tried.
        stopped_early: the J sweep stopped before ``max_basis``.
        rule: one line stating the decision rule with its numbers.
    """

    chosen: Candidate
    best: Candidate
    curve: list
    stopped_early: bool
    rule: str

    def describe(self) -> dict:
        return {
            "chosen": asdict(self.chosen),
            "best": asdict(self.best),
            "curve": [asdict(candidate) for candidate in self.curve],
            "stopped_early": self.stopped_early,
            "rule": self.rule,
        }


def choose_smallest(curve: list, tolerance_db: float, ceiling_db: float = math.inf) -> tuple[Candidate, Candidate]:
    """(chosen, best): the smallest candidate within ``tolerance_db`` of the best validation PSNR,
    every PSNR taken as at most ``ceiling_db``; best is the highest PSNR as measured."""
    if not curve:
        raise InputError("no candidates to choose from")
    best = max(curve, key=lambda candidate: candidate.psnr)
    top = min(best.psnr, ceiling_db)
    admissible = [candidate for candidate in curve if min(candidate.psnr, ceiling_db) >= top - tolerance_db]
    return min(admissible, key=lambda candidate: candidate.size), best


def select_model(evaluate: Callable[[int, bool], Candidate], config: SelectionConfig = SelectionConfig()) -> Selection:
    """Sweep J = 1, 2, ... with a Lambertian and a specular candidate each; choose the smallest good one.

    Args:
        evaluate: fits and scores one candidate, ``evaluate(num_basis, specular) -> Candidate``.
        config: sweep settings.

    Returns:
        Selection with the chosen candidate and the curve it was chosen from.
    """
    curve: list[Candidate] = []
    best_psnr, stale, stopped_early = -math.inf, 0, False
    for num_basis in range(1, config.max_basis + 1):
        scores = []
        for specular in LOBE_CHOICES:
            candidate = evaluate(num_basis, specular)
            curve.append(candidate)
            scores.append(min(candidate.psnr, config.psnr_ceiling_db))
        if max(scores) > best_psnr + config.min_improvement_db:
            stale = 0
        else:
            stale += 1
        best_psnr = max(best_psnr, max(scores))
        if stale >= config.patience and num_basis < config.max_basis:
            stopped_early = True
            break
    chosen, best = choose_smallest(curve, config.tolerance_db, config.psnr_ceiling_db)
    ceiling = f", PSNRs above {config.psnr_ceiling_db:g} dB counted as {config.psnr_ceiling_db:g}" if math.isfinite(config.psnr_ceiling_db) else ""
    rule = (
        f"smallest (J, specular) with validation PSNR >= best - {config.tolerance_db:g} dB "
        f"(best {best.psnr:.2f} dB at J={best.num_basis}, {'specular' if best.specular else 'Lambertian'}{ceiling}); "
        f"J sweep stops after {config.patience} J without a gain > {config.min_improvement_db:g} dB"
    )
    return Selection(chosen=chosen, best=best, curve=curve, stopped_early=stopped_early, rule=rule)


def light_spread(points: torch.Tensor, lights: torch.Tensor, falloff: Callable) -> dict:
    """How much the light directions and falloff vary across the object.

    Args:
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: distance falloff.

    Returns:
        ``{"max_direction_deg", "mean_direction_deg"}``: angle between each pixel's direction to
        each light and the centroid's; ``"max_falloff_ratio_deviation"``: max |f(x)/f(centroid) - 1|.

    Raises:
        InputError: the falloff is not positive and finite at a point or the centroid.
    """
    check_array("points", points, ("N", 3))
    check_array("lights", lights, ("K", 3))
    points, lights = points.double(), lights.double()
    centroid = points.mean(0, keepdim=True)

    centre_dirs, centre_distance = light_geometry(centroid, lights)

    def usable(values: torch.Tensor) -> torch.Tensor:
        if not bool(((values > 0) & torch.isfinite(values)).all()):
            raise InputError("light_spread: the falloff is not positive and finite over the object")
        return values

    centre_falloff = usable(torch.as_tensor(falloff(centre_distance), dtype=torch.float64))
    max_angle, angle_sum, max_ratio = 0.0, 0.0, 0.0
    for start in range(0, points.shape[0], 4096):
        dirs, distance = light_geometry(points[start : start + 4096], lights)
        cosine = (dirs * centre_dirs).sum(-1).clamp(-1.0, 1.0)
        angle = torch.rad2deg(torch.acos(cosine))
        max_angle = max(max_angle, float(angle.max()))
        angle_sum += float(angle.sum())
        ratio = usable(torch.as_tensor(falloff(distance), dtype=torch.float64) / centre_falloff)
        max_ratio = max(max_ratio, float((ratio - 1.0).abs().max()))
    return {
        "max_direction_deg": max_angle,
        "mean_direction_deg": angle_sum / (points.shape[0] * lights.shape[0]),
        "max_falloff_ratio_deviation": max_ratio,
    }


def choose_light_model(initial: InitialEstimate, emission: torch.Tensor, points: torch.Tensor, lights: torch.Tensor,
                       falloff: Callable, config: SelectionConfig = SelectionConfig()) -> dict:
    """Near or far field: render the starting point both ways and compare (see module docstring).

    Args:
        initial: photometric-stereo normals and albedo of the N pixels.
        emission: (M, K, 3) effective emission of the fit captures.
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: distance falloff.
        config: holds ``far_field_tolerance``.

    Returns:
        ``{"far_field": bool, "near_vs_far_relative_rms": float, "tolerance": float,
        "near_vs_far_psnr_db": float, **light_spread}``.
    """
    count = points.shape[0]
    white = torch.ones((1, 3))
    ones = torch.ones((count, 1))
    roughness = torch.ones(1)
    images = {}
    for far in (False, True):
        shading = render_under_patterns(initial.normal, points.float(), lights.float(), emission.float(), ones, white,
                                        None, roughness, falloff, far_field=far)
        images[far] = (shading * initial.albedo[None]).clamp(0.0, 1.0).double()
    difference = torch.sqrt(torch.mean((images[True] - images[False]) ** 2) / torch.mean(images[False] ** 2).clamp_min(1e-30))
    relative = float(difference)
    return {
        "far_field": relative < config.far_field_tolerance,
        "near_vs_far_relative_rms": relative,
        "tolerance": config.far_field_tolerance,
        "near_vs_far_psnr_db": pooled_psnr(images[True], images[False]),
        **light_spread(points, lights, falloff),
    }


def select_basis(
    problem: FitProblem,
    validation_emission: torch.Tensor,
    validation_images: torch.Tensor,
    template: FitConfig = FitConfig(),
    config: SelectionConfig = SelectionConfig(),
    initial: InitialEstimate | None = None,
    log: Callable[[int, bool, Candidate], None] | None = None,
) -> Selection:
    """Choose J and Lambertian / specular by validation relighting (``select_model`` over real fits).

    Args:
        problem: the captures the candidates are fitted on (must not include the validation
            images) and the scene geometry.
        validation_emission: (V, K, 3) emission of the validation images (e.g. exposed OLAT rows).
        validation_images: (V, N, 3) captured validation images in [0, 1].
        template: fit settings of every candidate; ``num_basis``, ``specular``, ``iterations`` and
            ``batch_pixels`` are replaced (the last two from ``config``).
        config: sweep settings.
        initial: starting point shared by all candidates (computed from the problem when None).
        log: optional callback ``log(num_basis, specular, candidate)`` after each candidate.

    Returns:
        Selection; each candidate's ``details`` holds its final training RMSE.
    """
    check_array("validation_emission", validation_emission, ("V", problem.lights.shape[0], 3), value_range=(0.0, math.inf))
    check_array("validation_images", validation_images, (validation_emission.shape[0], problem.points.shape[0], 3))
    if initial is None:
        initial = problem.initial_estimate()
    truth = validation_images.detach().double().clamp(0.0, 1.0)

    def evaluate(num_basis: int, specular: bool) -> Candidate:
        start = time.perf_counter()
        fit_config = dataclasses.replace(template, num_basis=num_basis, specular=specular, iterations=config.iterations,
                                         batch_pixels=config.batch_pixels)
        result = problem.fit(fit_config, initial)
        predicted = problem.relight(result, validation_emission).double().clamp(0.0, 1.0)
        candidate = Candidate(
            num_basis=num_basis,
            specular=specular,
            psnr=pooled_psnr(predicted, truth),
            rmse=float(torch.sqrt(torch.mean((predicted - truth) ** 2))),
            seconds=time.perf_counter() - start,
            details={"train_rmse": result.rmse_history[-1] if result.rmse_history else None},
        )
        if log is not None:
            log(num_basis, specular, candidate)
        return candidate

    return select_model(evaluate, config)
