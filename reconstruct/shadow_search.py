"""Attached-shadow search: the normal whose own shadow mask reproduces it.

The true Lambertian model with attached shadows,
    I[m, c] = a_c sum_k E[m, k, c] f_k max(0, l_k . n) = a_c b[m, c](s(n)) . n,
is linear in n within one shadow mask s(n) and piecewise linear overall. The least-squares fit for
a fixed mask is therefore a Gauss-Newton step of the true model. The search alternates fits and
mask updates, with a line search on the true residual, and restarts from other normals where the
answer is doubtful (the true residual is not convex in the normal).

The search talks to the data through an evaluator with two methods (index: (n,) long pixel
indices or None for all pixels; normals: (3, n)):
    masks_differ(index, first, second) -> (n,) bool, s(first) != s(second)
    evaluate(index, normal) -> Moments of the shadow masks s(normal)
Masks are never stored: a mask is a function of the normal, recomputed where needed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from reconstruct.pixel_solve import CONDITION_CAP, Moments, albedo_step, length, normal_condition, relative_residual, residual, tangent_basis, unit


@dataclass(eq=False)
class ShadowSearch:
    """State of the attached-shadow search of N pixels (updated in place).

    Invariant: ``moments`` are built from the shadow mask of ``normal``.

    Attributes:
        normal: (3, N) unit normals.
        albedo: (3, N) albedo for ``normal``, in the moments' normalised units.
        moments: moments of the shadow masks of ``normal``.
        objective: (N,) residual of ``normal`` with its own mask (normalised units).
        converged: (N,) bool.
    """

    normal: torch.Tensor
    albedo: torch.Tensor
    moments: Moments
    objective: torch.Tensor
    converged: torch.Tensor

    def take(self, index: torch.Tensor, other: "ShadowSearch", other_index: torch.Tensor) -> None:
        """Replace pixels ``index`` by pixels ``other_index`` of ``other``."""
        self.normal[:, index] = other.normal[:, other_index]
        self.albedo[:, index] = other.albedo[:, other_index]
        self.objective[index] = other.objective[other_index]
        self.converged[index] = other.converged[other_index]
        self.moments.assign(index, other.moments.subset(other_index, keep_vectors=True))


def shadow_search(evaluator, fit, initial_albedo, initial_normal, config) -> ShadowSearch:
    """Find normals that their own attached-shadow masks reproduce, by damped Gauss-Newton.

    ``fit`` (the least-squares solve for a fixed mask) proposes a step; it is accepted if it
    decreases the true residual (evaluated with the new normal's own mask), otherwise it is halved
    up to ``config.line_search_steps`` times, then the pixel stops. Without this safeguard the masks
    of ill-conditioned pattern sets oscillate. A pixel converges when the fit of its mask
    reproduces that mask, or when it stops at a kink of the model (a superpixel on its tangent
    plane, common with noise) with a rejected step shorter than ``config.kink_tolerance_deg``.
    Only pixels still moving are re-solved; the first iteration covers all and skips gathers.

    Args:
        evaluator: the data (see the module docstring).
        fit: (albedo (3, n), Moments) -> (albedo, normal, converged) for a fixed mask.
        initial_albedo: (3, N) starting albedo (moments' units).
        initial_normal: (3, N) starting unit normals.
        config: settings with damping, max_shadow_iterations, line_search_steps and
            kink_tolerance_deg (e.g. ``PSConfig``).

    Returns:
        The final ShadowSearch state.
    """
    count = initial_normal.shape[1]
    moments = evaluator.evaluate(None, initial_normal)
    state = ShadowSearch(
        normal=initial_normal.clone(),
        albedo=initial_albedo.clone(),
        moments=moments,
        objective=residual(initial_normal, moments, config.damping),
        converged=torch.zeros(count, dtype=torch.bool),
    )
    kink_tolerance = math.radians(config.kink_tolerance_deg)
    active = torch.arange(count)
    for iteration in range(config.max_shadow_iterations):
        if active.numel() == 0:
            break
        everyone = iteration == 0  # the first iteration covers every pixel and skips the gathers
        if everyone:
            active_moments, active_albedo, active_normal = state.moments, state.albedo, state.normal
        else:
            active_moments, active_albedo, active_normal = state.moments.subset(active), state.albedo[:, active], state.normal[:, active]
        # --- Gauss-Newton proposal: least-squares fit of the current masks.
        fitted_albedo, target, fit_converged = fit(active_albedo, active_moments)
        stable = ~evaluator.masks_differ(None if everyone else active, active_normal, target)
        # --- Same mask: the fit is that mask's least-squares optimum, so it cannot be worse.
        done = active[stable]
        state.normal[:, done], state.albedo[:, done] = target[:, stable], fitted_albedo[:, stable]
        state.converged[done] = fit_converged[stable]
        state.objective[done] = residual(target[:, stable], active_moments.subset(stable), config.damping)
        # --- New mask: line search on the true residual.
        moving = active[~stable]
        start, target = state.normal[:, moving], target[:, ~stable]
        pending = torch.arange(moving.numel())
        accepted = []
        for attempt in range(config.line_search_steps + 1):
            if pending.numel() == 0:
                break
            trial = target if attempt == 0 else unit(start[:, pending] + 0.5**attempt * (target[:, pending] - start[:, pending]))
            trial_moments = evaluator.evaluate(moving[pending], trial)
            trial_objective = residual(trial, trial_moments, config.damping)
            better = trial_objective < state.objective[moving[pending]]
            index = moving[pending[better]]
            kept_moments = trial_moments.subset(better, keep_vectors=True)
            state.normal[:, index], state.objective[index] = trial[:, better], trial_objective[better]
            state.moments.assign(index, kept_moments)
            state.albedo[:, index] = albedo_step(trial[:, better], kept_moments, config.damping)
            accepted.append(index)
            pending = pending[~better]
        stalled = moving[pending]
        state.converged[stalled] = length(target[:, pending] - start[:, pending]) <= kink_tolerance
        state.albedo[:, stalled] = albedo_step(start[:, pending], state.moments.subset(stalled), config.damping)
        active = torch.cat(accepted) if accepted else active[:0]
    return state


class _Replicated:
    """An evaluator over pixels ``pixels`` (long indices, repeats allowed) of another evaluator."""

    def __init__(self, base, pixels: torch.Tensor):
        self.base, self.pixels = base, pixels

    def _map(self, index):
        return self.pixels if index is None else self.pixels[index]

    def masks_differ(self, index, first, second):
        return self.base.masks_differ(self._map(index), first, second)

    def evaluate(self, index, normal):
        return self.base.evaluate(self._map(index), normal)


def restart_normals(view: torch.Tensor) -> list[torch.Tensor]:
    """Twelve starting normals (3, N) per pixel around the view directions (3, N): tilted 35 deg
    at 6 azimuths and 70 deg at 6 azimuths offset by 30 deg."""
    first, second = tangent_basis(view)
    starts = []
    for tilt_deg, offset_deg in ((35.0, 0.0), (70.0, 30.0)):
        tilt = math.radians(tilt_deg)
        for azimuth_deg in range(0, 360, 60):
            azimuth = math.radians(azimuth_deg + offset_deg)
            sideways = math.cos(azimuth) * first + math.sin(azimuth) * second
            starts.append(math.cos(tilt) * view + math.sin(tilt) * sideways)
    return starts


AMBIGUOUS_DEG = 2.0
"""Normals further apart than this (degrees) are different answers of an exactly determined pixel."""
AMBIGUOUS_RESIDUAL = 1e-3
"""Relative residual (``relative_residual``) up to which any fit counts as exact: float32's
cancellation floor. A pixel's alternative answer is as good as its chosen one if its relative
residual is at most the larger of this and 4 times the chosen one's."""


def restarted_search(evaluator, fit, initial_albedo, view, config, condition_of=normal_condition,
                     restart_residual: float | None = None, exactly_determined: torch.Tensor | None = None) -> tuple[ShadowSearch, torch.Tensor]:
    """``shadow_search`` from the view directions, restarted where the result is doubtful.

    With ill-conditioned pattern sets or near silhouettes a search can settle on a wrong
    self-consistent mask. Pixels whose condition number exceeds ``config.restart_condition`` or
    that did not converge are searched again from the 12 ``restart_normals`` (all starts in one
    batched search); the lowest true residual wins, ties keep the first result.

    Args:
        evaluator, fit, initial_albedo, config: as ``shadow_search`` (config also needs
            ``restart_condition``).
        view: (3, N) unit view directions, the first starting normals.
        condition_of: (normal (3, n), albedo (3, n), moment (3, 6, n)) -> (n,) condition numbers
            of the fit's model (default: the joint model's ``normal_condition``).
        restart_residual: if given, pixels whose relative residual (``relative_residual``)
            exceeds it are searched again too: a fit that matches its captures exactly for every
            mask (Woodham's per-channel fit with three captures a channel) settles on wrong
            masks at good condition numbers, which only the residual of the shared normal shows.
        exactly_determined: (N,) bool, pixels whose captures no self-consistent shadow mask can
            fail to fit (``photometric_stereo.PatternEvaluator.exactly_determined``: three grey
            patterns). They are searched from every start (the restarts' cost, 5-10x the search
            of three grey patterns), and where two self-consistent normals over
            ``AMBIGUOUS_DEG`` apart fit as well (``AMBIGUOUS_RESIDUAL``), the captures cannot
            tell them apart: the condition number is set to ``CONDITION_CAP`` (the pixel is
            flagged ill_conditioned).

    Returns:
        (state, condition (N,)) with the condition numbers of the chosen normals.
    """
    state = shadow_search(evaluator, fit, initial_albedo, view, config)
    condition = condition_of(state.normal, state.albedo, state.moments.moment)
    doubtful = (condition > config.restart_condition) | ~state.converged
    if restart_residual is not None:
        doubtful |= relative_residual(state.normal, state.moments) > restart_residual
    if exactly_determined is not None:
        doubtful |= exactly_determined
    doubtful = torch.nonzero(doubtful).squeeze(1)
    if doubtful.numel() == 0:
        return state, condition
    starts = restart_normals(view[:, doubtful])
    replicated = doubtful.repeat(len(starts))
    attempts = shadow_search(_Replicated(evaluator, replicated), fit, initial_albedo[:, replicated], torch.cat(starts, dim=1), config)
    if exactly_determined is not None:  # the first search's answers, before the restarts replace them
        first_normal, first_residual = state.normal[:, doubtful], relative_residual(state.normal[:, doubtful], state.moments.subset(doubtful))
    best_objective, best_start = attempts.objective.reshape(len(starts), -1).min(dim=0)
    better = torch.nonzero(best_objective < state.objective[doubtful]).squeeze(1)
    state.take(doubtful[better], attempts, best_start[better] * doubtful.numel() + better)
    condition[doubtful] = condition_of(state.normal[:, doubtful], state.albedo[:, doubtful], state.moments.moment[..., doubtful])
    if exactly_determined is not None:
        # Every answer found, the first search's included, against the chosen one.
        normals = torch.cat([first_normal, attempts.normal], dim=1).reshape(3, len(starts) + 1, -1)
        residuals = torch.cat([first_residual, relative_residual(attempts.normal, attempts.moments)]).reshape(len(starts) + 1, -1)
        chosen = state.normal[:, doubtful]
        as_good = residuals <= torch.clamp_min(4.0 * relative_residual(chosen, state.moments.subset(doubtful)), AMBIGUOUS_RESIDUAL)
        apart = (normals * chosen[:, None]).sum(0) < math.cos(math.radians(AMBIGUOUS_DEG))
        ambiguous = exactly_determined[doubtful] & (as_good & apart).any(0)
        condition[doubtful[ambiguous]] = CONDITION_CAP
    return state, condition
