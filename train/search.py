"""NLopt search of a heuristic family's parameters (`displex search`).

The objective is the mean angular error (degrees) of the analytic photometric stereo on the
training scenes, under patterns generated from the family's parameter vector:
    vector -> Family.generate (sharpness ``config.sharpness``) -> capture_scene (display, noise,
    clipping, quantisation, auto exposure) -> solve_ps -> mean angle to the true normals.
It is deterministic: every scene keeps one fixed subset of pixels (``pixels_per_scene``) and one
fixed noise draw (generator seeded with ``config.seed * 1000 + scene index``) for every
evaluation, so NLopt compares patterns, not noise draws. Gradient-based algorithms (LD_*) get the
gradient of this value by autograd, auto exposure included (``train.capture.exposure_with_gradient``:
without it, the on and off levels got gradients several to hundreds of times too large, in one
measurement of the wrong sign);
the angle is acos of the clamped cosine, as in training's uncapped 'angular' loss
(``train.learn.normal_loss``), so the value differs from the MAE by < 0.1 degree. It is smooth only
piecewise, and the gradient is that of the current piece: a pixel whose validity flag flips
switches between its estimate and the placeholder normal, and a nearly degenerate pixel (condition
number near the threshold) can switch between two self-consistent shadow masks under a change of
1e-7 in its captures. On small scene sets the value jumps by 0.02 to 0.2 degree at steps of 0.001
cell, far more than the gradient predicts. Derivative-free algorithms (the default LN_BOBYQA) cope;
LD_* ones can stall or fail on such jumps, which ends the search with the best point seen.

Search generates patterns at a low edge sharpness (4 per cell instead of the families' binary
default, ``patterns.families.DEFAULT_SHARPNESS``): there, split and block edges are binary and
their positions get no gradient, and a derivative-free search sees a staircase. The written pattern file holds the patterns exactly as evaluated (same sharpness,
soft edges), so its recorded MAE belongs to the file.

NLopt may stop by raising instead of returning (for example ``nlopt.RoundoffLimited`` from
LN_BOBYQA); the best point seen is kept inside the objective and returned in every case.
"""
from __future__ import annotations

import csv
import io
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import nlopt
import numpy as np
import torch
from tqdm import tqdm

from capture_sim.atomic import exclusive_output, staged_files, write_json, write_text
from capture_sim.errors import DisplexWarning, InputError, check_seed
from capture_sim.rig import DEFAULT_RIG, check_noise_scale, load_rig
from patterns.families import PRESETS, check_sharpness, default_vector, get_family
from patterns.io import save_patterns
from reconstruct.photometric_stereo import PSConfig, invalid_causes, solve_ps
from train.capture import capture_scene, exposure_with_gradient
from train.config_io import config_to_dict
from train.learn import check_logdir, config_record_path, normal_loss, summary_writer
from train.scene_pixels import ScenePixels, fixed_pixel_subsets, scene_pixels
from train.scene_sets import configured_scene_size, resolve_scenes

ALGORITHMS = ("LN_BOBYQA", "LN_COBYLA", "LN_SBPLX", "GN_CRS2_LM", "GN_ESCH", "GN_DIRECT_L", "LD_MMA", "LD_LBFGS")
"""NLopt algorithms `displex search` accepts: local derivative-free (LN), global (GN), gradient-based (LD)."""

GRADIENT_ALGORITHMS = frozenset(name for name in ALGORITHMS if name.startswith("LD_"))
QUADRATIC_MEMORY_ALGORITHMS = frozenset({"LN_BOBYQA", "LN_COBYLA"})
MAX_QUADRATIC_PARAMETERS = 2000
"""Largest parameter count for BOBYQA and COBYLA: their O(P^2) state is ~2 GB by
P ~ 20000 (a random family at M = 50), past which the machine runs out of memory."""
MAX_EVALUATIONS = 2**31 - 1
"""Largest ``maxeval`` (NLopt stores it in a C int)."""

_RESULT_NAMES = {
    nlopt.SUCCESS: "success",
    nlopt.STOPVAL_REACHED: "stopval reached",
    nlopt.FTOL_REACHED: "ftol reached",
    nlopt.XTOL_REACHED: "xtol reached",
    nlopt.MAXEVAL_REACHED: "maxeval reached",
    nlopt.MAXTIME_REACHED: "maxtime reached",
}


@dataclass(frozen=True)
class SearchConfig:
    """Settings of one NLopt search over a heuristic family (TOML files in configs/search/)."""

    family: str = "tri_complementary"
    """Family to search (``patterns.families.FAMILIES``)."""
    num_patterns: int = 2
    """M, the number of patterns."""
    algorithm: str = "LN_BOBYQA"
    """NLopt algorithm, one of ``ALGORITHMS``."""
    maxeval: int = 60
    """Largest number of objective evaluations (the start point counts as the first)."""
    maxtime: float | None = None
    """Wall-clock limit of the search in seconds; None or 0 = no limit."""
    xtol_rel: float = 1e-4
    """Stop when a step changes every parameter by less than this fraction of its value."""
    ftol_abs: float = 1e-3
    """Stop when a step changes the objective by less than this many degrees."""
    initial_step: float = 0.1
    """First step of local algorithms, as a fraction of each parameter's bound range."""
    seed: int = 0
    """Seed of NLopt's random choices (``nlopt.srand``), the pixel subsets, the noise draws and the
    start values of the random families (mono_random, tri_random, gray_noise)."""
    start: str = "default"
    """Start point: the family's preset ``"default"`` (lo 0, hi 1 where the family has levels) or
    ``"ddps"`` (published)."""
    scenes: tuple[str, ...] = ()
    """Scene files or folders the search optimises on; empty = the default synthetic train split."""
    noise_scale: float = 1.0
    """Multiplier of the rig's noise variances (0 = noise-free, unquantised)."""
    rig: str = DEFAULT_RIG
    """Rig preset or TOML path."""
    scene_size: tuple[int, int] | None = None
    """Image size (height, width) of the default synthetic scenes; None (unset) is replaced on
    construction by a quarter of the rig camera's resolution (``capture_sim.synth.default_scene_size``:
    128 x 153 on the reference rig)."""
    scene_seed: int = 0
    """Seed of the default synthetic scenes."""
    sharpness: float = 4.0
    """Edge slope (1/cells) of split and block edges during the search and in the written file;
    low enough for useful gradients and a smooth objective (the families' default,
    ``patterns.families.DEFAULT_SHARPNESS``, makes binary edges)."""
    pixels_per_scene: int = 3000
    """Fixed random pixels per scene in the objective (0 = every masked pixel)."""

    def __post_init__(self):
        get_family(self.family)
        object.__setattr__(self, "scene_size", configured_scene_size(self.scene_size, self.rig))
        if self.algorithm not in ALGORITHMS:
            raise InputError(f"unknown NLopt algorithm {self.algorithm!r}; algorithms: {', '.join(ALGORITHMS)}")
        if self.start not in PRESETS:
            raise InputError(f"start must be one of {', '.join(PRESETS)}, got {self.start!r}")
        if not 1 <= self.maxeval <= MAX_EVALUATIONS:
            raise InputError(f"maxeval must be in [1, {MAX_EVALUATIONS}], got {self.maxeval}")
        check_seed("seed", self.seed)
        check_seed("scene_seed", self.scene_seed)
        if self.maxtime is not None and not 0 <= self.maxtime < math.inf:
            raise InputError(f"maxtime must be >= 0 seconds (0 = no limit), got {self.maxtime}")
        check_noise_scale("noise_scale", self.noise_scale)
        for name in ("xtol_rel", "ftol_abs"):
            if not 0 <= getattr(self, name) < math.inf:
                raise InputError(f"{name} must be a finite number >= 0, got {getattr(self, name)!r}")
        if not 0 < self.initial_step <= 1:
            raise InputError(f"initial_step must lie in (0, 1], got {self.initial_step!r}")
        if self.pixels_per_scene < 0:
            raise InputError(f"pixels_per_scene must be >= 0 (0 = every pixel), got {self.pixels_per_scene!r}")
        check_sharpness(self.sharpness)


# ---------------------------------------------------------------------------------------------
# Generic bounded minimisation with NLopt (no knowledge of patterns: tests drive it directly)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Minimum:
    """Outcome of ``minimise``.

    Attributes:
        best_x: (P,) float64 best point seen.
        best_value: its objective value.
        start_value: objective value at the start point.
        history: [(x (P,), value)] of every evaluation in order (the start first).
        stop_reason: why the search ended (NLopt's result, or the exception NLopt raised).
        seconds: wall time of the whole search, start evaluation included.
    """

    best_x: np.ndarray
    best_value: float
    start_value: float
    history: list
    stop_reason: str
    seconds: float


CACHED_POINTS = 64
"""Evaluations ``_Tracker`` remembers: algorithms that ask for a point again (LN_SBPLX returns to
its start) are answered without spending an evaluation of the budget (``minimise`` lets NLopt
make ``NLOPT_REQUESTS_PER_EVALUATION`` times as many requests as the budget has evaluations)."""

NLOPT_REQUESTS_PER_EVALUATION = 4
"""NLopt's own request limit over ``maxeval``: it counts repeated points, which the cache answers
without spending the budget; the budget itself is enforced by ``_Tracker``."""


class _Tracker:
    """The NLopt callback: evaluates, records, keeps the best point, enforces the budget.

    Exceptions, KeyboardInterrupt included, never cross NLopt's C code (some algorithms, e.g.
    GN_CRS2_LM, mangle them into chained SystemErrors): the callback stores the exception, asks
    NLopt to stop and returns the best value so far; ``minimise`` re-raises it.
    """

    def __init__(self, evaluate, maxeval: int, low: np.ndarray, high: np.ndarray, on_evaluation, deadline: float | None = None):
        self.evaluate = evaluate
        self.low, self.high = low, high
        self.maxeval = maxeval
        self.deadline = deadline
        self.on_evaluation = on_evaluation
        self.history: list = []
        self.best_x: np.ndarray | None = None
        self.best_value = math.inf
        self.error: BaseException | None = None
        self.optimiser = None
        self.out_of_time = False
        self._cache: dict = {}

    def __call__(self, x: np.ndarray, grad: np.ndarray) -> float:
        try:
            return self._call(x, grad)
        except BaseException as err:  # noqa: BLE001  (re-raised or reported after NLopt returns; Ctrl-C too)
            self.error = self.error or err
            self._stop()
            grad[:] = 0.0
            return self.best_value

    def _call(self, x: np.ndarray, grad: np.ndarray) -> float:
        # Some algorithms step a rounding error outside the bounds; the generators reject that.
        # + 0.0 turns -0.0 into 0.0: the same point must have one cache key (LN_BOBYQA asks for
        # the start again with a zero's sign flipped).
        x = np.clip(np.asarray(x, dtype=np.float64), self.low, self.high) + 0.0
        key = x.tobytes()
        need_gradient = grad.size > 0
        cached = self._cache.get(key)
        # Some algorithms (LD_LBFGS's line search) do not check NLopt's own time limit.
        self.out_of_time = self.out_of_time or (self.deadline is not None and bool(self.history) and time.perf_counter() >= self.deadline)
        if cached is not None and (cached[1] is not None or not need_gradient):
            value, gradient = cached
        elif len(self.history) >= self.maxeval or self.error is not None or self.out_of_time:
            self._stop()
            grad[:] = 0.0
            return self.best_value
        else:
            value, gradient = self.evaluate(x.copy(), need_gradient)
            value = float(value)
            if not math.isfinite(value):
                self.error = FloatingPointError(f"the objective returned {value} at {x.tolist()}")
                self._stop()
                grad[:] = 0.0
                return self.best_value
            if len(self._cache) >= CACHED_POINTS:
                del self._cache[next(iter(self._cache))]  # the oldest
            self._cache[key] = (value, gradient)
            self.history.append((x, value))
            if value < self.best_value or self.best_x is None:
                self.best_value, self.best_x = value, x
            self.on_evaluation(len(self.history) - 1, x, value, self.best_value)
        if need_gradient:
            grad[:] = gradient
        return value

    def _stop(self) -> None:
        if self.optimiser is not None:
            self.optimiser.force_stop()


def check_parameter_count(algorithm: str, count: int) -> None:
    """Raise ``InputError`` if ``algorithm`` cannot hold ``count`` parameters in memory.

    ``minimise`` calls it, and ``run_search`` calls it before loading scenes, so a search that
    would be refused fails at once, not after minutes of scene synthesis.

    Args:
        algorithm: one of ``ALGORITHMS``.
        count: P, the number of parameters searched.
    """
    if algorithm in QUADRATIC_MEMORY_ALGORITHMS and count > MAX_QUADRATIC_PARAMETERS:
        raise InputError(
            f"{algorithm} keeps state that grows with the square of the parameter count, and this search has "
            f"{count} parameters (at most {MAX_QUADRATIC_PARAMETERS}): use LD_MMA or LD_LBFGS, or a smaller M"
        )


# nlopt 2.11 raises its own exception classes, which no longer derive from RuntimeError and
# ValueError (older releases raise those built-ins).
_NLOPT_RUNTIME_ERROR = getattr(nlopt, "runtime_error", RuntimeError)
_NLOPT_INVALID_ARGUMENT = getattr(nlopt, "invalid_argument", ValueError)
STOPPING_ERRORS = (nlopt.RoundoffLimited, nlopt.ForcedStop, _NLOPT_RUNTIME_ERROR, RuntimeError)
"""What NLopt raises when it stops early (a generic failure included, e.g. LD_LBFGS's line search
on a piecewise-smooth objective); the best point seen is still the answer."""


def minimise(
    evaluate: Callable[[np.ndarray, bool], tuple[float, np.ndarray | None]],
    start: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    algorithm: str,
    maxeval: int,
    maxtime: float | None = None,
    xtol_rel: float = 1e-4,
    ftol_abs: float = 1e-3,
    initial_step: float = 0.1,
    seed: int = 0,
    on_evaluation: Callable[[int, np.ndarray, float, float], None] | None = None,
) -> Minimum:
    """Minimise ``evaluate`` within bounds with an NLopt algorithm, robust to early stops.

    The start point is evaluated first (so every algorithm, global ones included, reports the
    start value and never returns anything worse); NLopt's own request for it is served from a
    cache. NLopt exceptions that mean "stopped early" (``STOPPING_ERRORS``, or
    ``nlopt.RoundoffLimited`` / ``nlopt.ForcedStop`` raised by ``evaluate`` itself) end the search
    with the best point seen; any other exception from ``evaluate`` is re-raised.

    Args:
        evaluate: (x (P,) float64, need_gradient) -> (value, (P,) gradient or None).
        start: (P,) start point within the bounds.
        low, high: (P,) finite bounds.
        algorithm: one of ``ALGORITHMS``.
        maxeval: largest number of evaluations (the start included), >= 1.
        maxtime: wall-clock limit in seconds; None or 0 = no limit.
        xtol_rel, ftol_abs: NLopt's relative parameter and absolute objective tolerances.
        initial_step: first step as a fraction of each bound range (local algorithms).
        seed: ``nlopt.srand`` seed (population-based and random algorithms).
        on_evaluation: called after every new evaluation with (index, x, value, best value so far).

    Returns:
        Minimum with the best point, the start value and the whole history.
    """
    if algorithm not in ALGORITHMS:
        raise InputError(f"unknown NLopt algorithm {algorithm!r}; algorithms: {', '.join(ALGORITHMS)}")
    if maxeval < 1:
        raise InputError(f"maxeval must be >= 1, got {maxeval}")
    start, low, high = (np.asarray(v, dtype=np.float64).ravel() for v in (start, low, high))
    if not (start.shape == low.shape == high.shape) or start.size == 0:
        raise InputError(f"start and bounds must have one equal non-zero length, got {start.size}, {low.size}, {high.size}")
    if not (np.isfinite(low).all() and np.isfinite(high).all() and (low <= high).all()):
        raise InputError("bounds must be finite with low <= high")
    if ((start < low) | (start > high)).any():
        raise InputError("the start point lies outside the bounds")
    check_parameter_count(algorithm, start.size)
    begun = time.perf_counter()
    tracker = _Tracker(evaluate, int(maxeval), low, high, on_evaluation or (lambda *_: None), begun + maxtime if maxtime else None)
    # Gradient algorithms ask for the start's gradient first: compute it now so the cache serves it.
    tracker(start.copy(), np.empty(start.size if algorithm in GRADIENT_ALGORITHMS else 0))
    if tracker.error is not None:
        raise tracker.error
    stop_reason = "maxeval reached"
    if maxeval > 1:
        nlopt.srand(int(seed))
        optimiser = nlopt.opt(getattr(nlopt, algorithm), start.size)
        tracker.optimiser = optimiser
        optimiser.set_lower_bounds(low)
        optimiser.set_upper_bounds(high)
        optimiser.set_min_objective(tracker)
        optimiser.set_maxeval(int(min(MAX_EVALUATIONS, NLOPT_REQUESTS_PER_EVALUATION * maxeval)))
        if maxtime:
            optimiser.set_maxtime(max(1e-3, maxtime - (time.perf_counter() - begun)))
        optimiser.set_xtol_rel(xtol_rel)
        optimiser.set_ftol_abs(ftol_abs)
        # Zero-width bounds would give a zero step, which NLopt rejects.
        optimiser.set_initial_step(np.maximum(initial_step * (high - low), 1e-9))
        try:
            optimiser.optimize(start.copy())
            stop_reason = _RESULT_NAMES.get(optimiser.last_optimize_result(), f"nlopt result {optimiser.last_optimize_result()}")
        except STOPPING_ERRORS as err:
            stop_reason = f"stopped: {type(err).__name__} {err}".strip()
        except (_NLOPT_INVALID_ARGUMENT, ValueError) as err:
            raise InputError(f"NLopt rejected the search problem ({algorithm}, {start.size} parameters): {err}") from None
        if tracker.error is not None:
            if not isinstance(tracker.error, (nlopt.RoundoffLimited, nlopt.ForcedStop)):
                raise tracker.error
            stop_reason = f"stopped: {type(tracker.error).__name__} {tracker.error}".strip()
        elif len(tracker.history) >= maxeval:
            stop_reason = "maxeval reached"
        elif tracker.out_of_time:
            stop_reason = "maxtime reached"
        elif stop_reason == "maxeval reached":  # NLopt's request limit, repeated points included
            stop_reason = f"stopped: NLopt's own request limit ({NLOPT_REQUESTS_PER_EVALUATION} x maxeval, repeated points included)"
    return Minimum(
        best_x=tracker.best_x,
        best_value=tracker.best_value,
        start_value=tracker.history[0][1],
        history=tracker.history,
        stop_reason=stop_reason,
        seconds=time.perf_counter() - begun,
    )


# ---------------------------------------------------------------------------------------------
# The pattern objective
# ---------------------------------------------------------------------------------------------


def prepare_scenes(paths, split: str, rig, size: tuple[int, int], seed: int) -> list[ScenePixels]:
    """Scenes with true normals, from files/folders or the default synthetic ``split``."""
    scenes = [scene_pixels(scene, rig, require_normals=True) for scene in resolve_scenes(tuple(paths), split, rig, size, seed, separated=False)]
    if not scenes:
        raise InputError("no scenes to search on")
    return scenes


class PatternObjective:
    """Mean angular error (degrees) over scenes of patterns generated from a family's vector.

    Args:
        family: family name.
        num_patterns: M.
        scenes: prepared scenes with true normals.
        rows, cols: display grid R x C.
        noise_scale: multiplier of the rig's noise variances.
        sharpness: edge slope used to generate patterns (1/cells).
        pixels_per_scene: fixed random pixel subset per scene (0 = all pixels).
        seed: seed of the pixel subsets and the noise draws.
        ps_config: solver settings.
    """

    def __init__(self, family: str, num_patterns: int, scenes: list[ScenePixels], rows: int, cols: int,
                 noise_scale: float = SearchConfig.noise_scale, sharpness: float = SearchConfig.sharpness,
                 pixels_per_scene: int = SearchConfig.pixels_per_scene, seed: int = 0,
                 ps_config: PSConfig = PSConfig()):
        self.family = get_family(family)
        self.family.check(num_patterns, rows, cols)
        self.num_patterns, self.rows, self.cols = num_patterns, rows, cols
        self.scenes, self.noise_scale, self.sharpness, self.seed, self.ps_config = scenes, noise_scale, sharpness, seed, ps_config
        self.columns = fixed_pixel_subsets(scenes, pixels_per_scene, seed)
        self.invalid_fractions: list[float] = []
        """Per scene, the share of pixels the solver flagged invalid at the latest evaluation."""
        self.flag_shares: dict[str, float] = {}
        """Per solver flag, the share of the search pixels carrying it at the latest evaluation
        that left every pixel of every scene invalid."""

    def patterns(self, vector: np.ndarray | torch.Tensor) -> torch.Tensor:
        """(M, R, C, 3) float32 patterns of a (P,) parameter vector (differentiable in a tensor)."""
        values = torch.as_tensor(vector, dtype=torch.float64)
        return self.family.generate(values, self.num_patterns, self.rows, self.cols, self.sharpness).float()

    def value(self, patterns: torch.Tensor) -> torch.Tensor:
        """Scalar mean over scenes of the mean angle (degrees) over each scene's pixel subset."""
        losses, invalid, flags = [], [], []
        for index, (pixels, columns) in enumerate(zip(self.scenes, self.columns)):
            noise = torch.Generator().manual_seed(self.seed * 1000 + index)
            # The same value either way (bit for bit); with a gradient, auto exposure's share in it
            # too (a brighter set is exposed for less time, which takes back most of its gain).
            exposure = exposure_with_gradient(pixels, patterns) if patterns.requires_grad and torch.is_grad_enabled() else "auto"
            capture = capture_scene(pixels, patterns, self.noise_scale, exposure, noise, columns)
            points = pixels.points if columns is None else pixels.points[columns]
            truth = pixels.normal if columns is None else pixels.normal[columns]
            result = solve_ps(capture.captures, capture.emission, points, pixels.lights(), pixels.rig.falloff, self.ps_config)
            losses.append(normal_loss(result.normal, truth, "angular"))
            invalid.append(float((~result.valid).float().mean()) if result.valid.numel() else 1.0)
            flags.append(result.flags)
        self.invalid_fractions = invalid
        if invalid and min(invalid) == 1.0:  # only the all-invalid warning reads them
            self.flag_shares = {name: float(torch.cat([f[name] for f in flags]).float().mean()) for name in flags[0]}
        return torch.rad2deg(torch.stack(losses).mean())

    def __call__(self, vector: np.ndarray, need_gradient: bool) -> tuple[float, np.ndarray | None]:
        """(value in degrees, (P,) gradient or None) at a (P,) float64 vector."""
        if not need_gradient:
            with torch.no_grad():
                return float(self.value(self.patterns(vector))), None
        values = torch.tensor(vector, dtype=torch.float64, requires_grad=True)
        value = self.value(self.patterns(values))
        (gradient,) = torch.autograd.grad(value, values, allow_unused=True)
        gradient = np.zeros(values.shape) if gradient is None else gradient.numpy()
        # A non-finite gradient must not reach NLopt: treat that point as flat.
        return float(value.detach()), np.nan_to_num(gradient, nan=0.0, posinf=0.0, neginf=0.0)


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------


def trace_path(out: Path) -> Path:
    """``<out stem>.trace.csv`` next to the pattern file: the trace of the finished search."""
    return out.with_name(out.stem + ".trace.csv")


def partial_trace_path(out: Path) -> Path:
    """``<out stem>.trace.partial.csv`` next to the pattern file: the trace flushed during a search.

    A separate name, so that an interrupted search never leaves a ``.trace.csv`` beside the pattern
    file, chart and config record of an earlier finished search with the same ``out``.
    """
    return out.with_name(out.stem + ".trace.partial.csv")


def trace_chart_path(out: Path) -> Path:
    """``<out stem>.trace.png`` next to the pattern file."""
    return out.with_name(out.stem + ".trace.png")


def output_files(out: Path) -> list[tuple[str, Path]]:
    """(what, path) of the files a search writing patterns to ``out`` writes, the partial trace
    included (written while it runs and removed when it finishes)."""
    return [("--out", out), ("trace", trace_path(out)), ("partial trace", partial_trace_path(out)),
            ("trace chart", trace_chart_path(out)), ("config record", config_record_path(out))]


def trace_csv(names: list[str], history: list) -> str:
    """CSV text: index, every parameter by name, mae, best_so_far (one row per evaluation)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["index", *names, "mae", "best_so_far"])
    best = math.inf
    for index, (x, value) in enumerate(history):
        best = min(best, value)
        writer.writerow([index, *(repr(float(v)) for v in x), repr(float(value)), repr(float(best))])
    return buffer.getvalue()


def trace_figure(history: list, title: str, caption: str, probes: int = 0):
    """Figure of the objective (degrees) and the best so far against the evaluation index; with
    ``probes`` > 0 (LN_BOBYQA: 2 P + 1), a line where the algorithm's probes around the start end
    and its steps begin (a best-so-far drop before it is a probe, not progress)."""
    from train.figures import plt

    values = np.array([value for _, value in history])
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    ax.plot(np.arange(values.size), values, "o", markersize=3, alpha=0.6, label="evaluation")
    ax.plot(np.arange(values.size), np.minimum.accumulate(values), "-", drawstyle="steps-post", linewidth=2, label="best so far")
    if 0 < probes < values.size:
        ax.axvline(probes - 0.5, color="gray", linestyle=":", linewidth=1, label=f"first steps after {probes} probes")
    elif probes >= values.size > 0:  # the run ended among the probes: no step was taken
        title = f"{title}\n(all {values.size} evaluations were probes around the start: no step taken)"
    ax.set_xlabel("evaluation index")
    ax.xaxis.get_major_locator().set_params(integer=True)  # evaluations are counted, not measured
    ax.set_ylabel("mean angular error (deg)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.text(0.5, -0.02, caption, ha="center", va="top", fontsize=8, wrap=True)
    fig.tight_layout()
    return fig


def _remove_file(path: Path) -> None:
    """Delete ``path`` if a file or link stands there (anything else is left for ``write_text`` to
    refuse by name)."""
    if path.is_file() or path.is_symlink():
        path.unlink()


def start_text(start: str, sharpness: float) -> str:
    """'the family's default parameters at sharpness 4': what a search's start MAE measures."""
    return f"the family's {start} parameters at sharpness {sharpness:g}"


def _search_meta(config: SearchConfig, rig, names: list[str], start, found, scenes: list) -> dict:
    """The pattern file's meta of a finished search (``found``: ``minimise``'s result; ``scenes``:
    the prepared search scenes)."""
    return {
        "family": config.family,
        "algorithm": config.algorithm,
        "made_by": "displex search",
        "rig": rig.name,
        "num_patterns": config.num_patterns,
        "parameter_names": names,
        "parameters": {name: float(value) for name, value in zip(names, found.best_x)},
        "start_parameters": {name: float(value) for name, value in zip(names, start)},
        "start_mae": found.start_value,
        "best_mae": found.best_value,
        "evaluations": len(found.history),
        "stop_reason": found.stop_reason,
        "sharpness": config.sharpness,
        "start": config.start,
        "objective": (
            f"mean over {len(scenes)} training scenes of the mean angular error (deg) of solve_ps over "
            f"{'all' if not config.pixels_per_scene else f'at most {config.pixels_per_scene} fixed'} pixels per scene, "
            f"noise scale {config.noise_scale:g}, fixed noise seed"
        ),
        "scenes": [pixels.name for pixels in scenes],
        "config": config_to_dict(config),
    }


def run_search(config: SearchConfig, out: Path, logdir: Path | None = None, progress: bool = True, own_logdir: bool = False) -> dict:
    """Search a family's parameters with NLopt and write the best patterns.

    Writes ``out`` (pattern .npz, patterns exactly as evaluated, meta with the family, algorithm,
    parameters, start and best MAE, evaluations), ``<out stem>.trace.csv`` (every evaluation),
    ``<out stem>.trace.png`` (objective against evaluation index) and ``<out stem>.config.json``;
    TensorBoard scalars under ``logdir`` if given. While it runs, every 10 evaluations go to
    ``<out stem>.trace.partial.csv`` (a stale one from an earlier run is removed when the
    evaluations start, after every input was checked); a finished search removes it, and a search
    interrupted (Ctrl-C, an error) leaves it, holding every evaluation made, and writes none of
    the other files (they are staged and replace an earlier search's together).

    Args:
        config: search settings.
        out: output pattern file (.npz).
        logdir: TensorBoard folder, or None.
        progress: show a tqdm bar over evaluations.
        own_logdir: ``logdir`` holds this output's runs alone (e.g. compare's): an earlier,
            interrupted search's events there are hidden (a search starts over). Other runs
            sharing a folder keep theirs.

    Returns:
        The pattern file's meta dict plus the run's wall ``seconds`` and the ``pattern_file``,
        ``trace_csv`` and ``trace_png`` paths.
    """
    # A second search on the same output would share its partial trace and replace its result.
    with exclusive_output(out, "search"):
        return _search(config, Path(out), logdir, progress, own_logdir)


def check_search_setup(config: SearchConfig, rig) -> np.ndarray:
    """Refuse a family that does not support M on the rig's grid, or more parameters than the
    algorithm takes, before any scene is read; return the start vector (P,).

    Raises:
        InputError: as said (``Family.check``, ``check_parameter_count``).
    """
    get_family(config.family).check(config.num_patterns, rig.rows, rig.cols)
    start = default_vector(config.family, config.num_patterns, rig.rows, rig.cols, config.start, config.seed).numpy()
    check_parameter_count(config.algorithm, start.size)
    return start


def _search(config: SearchConfig, out: Path, logdir: Path | None, progress: bool, own_logdir: bool) -> dict:
    from train.figures import save_figure

    check_logdir(logdir, output_files(out))  # before the scenes, which can take a while
    rig = load_rig(config.rig)
    start = check_search_setup(config, rig)  # before the scenes, which can take minutes
    family = get_family(config.family)
    parameters = family.parameters(config.num_patterns, rig.rows, rig.cols, config.start, config.seed)
    names = [p.name for p in parameters]
    low, high = family.bounds(config.num_patterns, rig.rows, rig.cols)
    trace, partial = trace_path(out), partial_trace_path(out)
    scenes = prepare_scenes(config.scenes, "train", rig, config.scene_size, config.scene_seed)
    objective = PatternObjective(config.family, config.num_patterns, scenes, rig.rows, rig.cols, config.noise_scale,
                                 config.sharpness, config.pixels_per_scene, config.seed)
    # Every input is checked: now a partial trace left by an earlier interrupted run goes, as it
    # would pass for this run's if this one were interrupted before its first flush.
    _remove_file(partial)
    writer = summary_writer(logdir, 0 if own_logdir else None)
    bar = tqdm(total=config.maxeval, desc=f"search {config.family} M={config.num_patterns} {config.algorithm}", unit="eval", disable=not progress)
    seen: list = []

    def on_evaluation(index, x, value, best):
        if index == 0 and objective.invalid_fractions and min(objective.invalid_fractions) == 1.0:
            warnings.warn(f"the start patterns of {config.family} (M = {config.num_patterns}) leave every pixel of every search "
                          f"scene invalid ({invalid_causes(objective.flag_shares)}): the MAE cannot guide the search",
                          DisplexWarning, stacklevel=2)
        seen.append((x, value))
        bar.update(1)
        bar.set_postfix(mae=f"{value:.2f}", best=f"{best:.2f}")
        if writer is not None:
            writer.add_scalar("search/mae_deg", value, index)
            writer.add_scalar("search/best_mae_deg", best, index)
        if index % 10 == 9:
            write_text(partial, trace_csv(names, seen))

    try:
        found = minimise(objective, start, low, high, config.algorithm, config.maxeval, config.maxtime, config.xtol_rel,
                         config.ftol_abs, config.initial_step, config.seed, on_evaluation)
        meta = _search_meta(config, rig, names, start, found, scenes)
        chart = trace_chart_path(out)
        caption = (f"{meta['objective']}; {len(found.history)} evaluations, stop: {found.stop_reason}; "
                   f"start ({start_text(config.start, config.sharpness)}) {found.start_value:.2f} deg, best {found.best_value:.2f} deg")
        # The four outputs replace an earlier search's together (the pattern file last).
        with staged_files(out.parent, last=(out.name,)) as staging:
            save_patterns(staging / out.name, objective.patterns(found.best_x).numpy(), meta)
            write_json(staging / config_record_path(out).name, meta["config"])
            write_text(staging / trace.name, trace_csv(names, found.history))
            probes = 2 * len(names) + 1 if config.algorithm == "LN_BOBYQA" else 0  # its initial quadratic model's points
            save_figure(trace_figure(found.history, f"NLopt {config.algorithm}: {config.family}, M = {config.num_patterns}", caption, probes),
                        staging / chart.name)
    except BaseException:
        if seen:  # stopped (Ctrl-C, an error): every evaluation made so far, not only the last flush
            write_text(partial, trace_csv(names, seen))
        raise
    finally:
        bar.close()
        if writer is not None:
            writer.close()
    _remove_file(partial)
    # The run time is returned, not kept in the file: a search repeated with the same seed writes the same bytes.
    return {**meta, "seconds": found.seconds, "pattern_file": str(out), "trace_csv": str(trace), "trace_png": str(chart)}
