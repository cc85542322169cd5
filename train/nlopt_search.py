"""`displex search`: NLopt over the continuous parameters of a heuristic pattern family.

The objective is the mean angular error (degrees) over a fixed random subset of pixels of each
training scene, with fixed noise, reconstructed by the fixed-iteration solver used for learning
(``reconstruct.unrolled_ps``), so it is deterministic and differentiable: gradient-based
algorithms get the gradient torch computes through family -> simulator -> solver. Families are
generated with soft edges (``sharpness``) so that split and block positions have gradients; the
pattern file holds exactly what was evaluated.
"""
from __future__ import annotations

import csv
import io
import time
from dataclasses import dataclass
from pathlib import Path

import nlopt
import numpy as np
import torch
from tqdm import tqdm

from capture_sim.atomic import write_text
from capture_sim.errors import InputError
from capture_sim.rig import DEFAULT_RIG, load_rig
from patterns.families import FAMILIES, get_family
from patterns.io import save_patterns
from reconstruct.unrolled_ps import solve_ps_unrolled
from train.capture import capture_scene
from train.figures import save_figure
from train.scene_pixels import scene_pixels
from train.scene_sets import resolve_scenes

ALGORITHMS = ("LN_BOBYQA", "LN_COBYLA", "LN_SBPLX", "GN_CRS2_LM", "GN_ESCH", "GN_DIRECT_L", "LD_MMA", "LD_LBFGS")


@dataclass(frozen=True)
class SearchConfig:
    """What `displex search` does."""

    family: str
    """Heuristic family (DESIGN section 6 names)."""
    num_patterns: int
    """M."""
    algorithm: str = "LN_BOBYQA"
    """NLopt algorithm, one of ALGORITHMS (LD_* use torch gradients)."""
    maxeval: int = 40
    """Stop after this many objective evaluations."""
    maxtime: float = 0.0
    """Stop after this many seconds (0 = no limit)."""
    xtol_rel: float = 1e-4
    """Stop when parameters change by less than this, relatively."""
    seed: int = 0
    """Seed of NLopt's stochastic algorithms, of the pixel subset and of the noise."""
    scenes: tuple[str, ...] = ()
    """Scenes to optimise on; empty = the default synthetic training split."""
    noise_scale: float = 1.0
    """Multiplier of the rig's noise variances."""
    rig: str = DEFAULT_RIG
    """Rig preset or TOML path."""
    sharpness: float = 4.0
    """Edge slope (1/cells) of splits and blocks while searching, so that positions have gradients."""
    pixels_per_scene: int = 2000
    """Size of the fixed pixel subset of every scene in the objective."""

    def __post_init__(self):
        if self.family not in FAMILIES:
            raise InputError(f"unknown family {self.family!r}; choose from {', '.join(FAMILIES)}")
        if self.algorithm not in ALGORITHMS:
            raise InputError(f"unknown algorithm {self.algorithm!r}; choose from {', '.join(ALGORITHMS)}")
        if self.maxeval < 1 or self.maxtime < 0:
            raise InputError("maxeval must be >= 1 and maxtime >= 0")


class _Objective:
    """Mean angular error of a parameter vector; keeps every evaluation and the best point."""

    def __init__(self, config: SearchConfig, scenes, rows: int, cols: int, progress: bool):
        self.config, self.scenes, self.rows, self.cols = config, scenes, rows, cols
        self.family = get_family(config.family)
        generator = torch.Generator().manual_seed(config.seed)
        self.columns = [torch.randperm(p.num_pixels, generator=generator)[: config.pixels_per_scene] for p in scenes]
        self.trace: list[tuple[np.ndarray, float]] = []
        self.best_x, self.best_value = None, float("inf")
        self.bar = tqdm(total=config.maxeval, desc=f"search {config.family} {config.algorithm}", disable=not progress, unit="eval")

    def patterns(self, x: np.ndarray) -> torch.Tensor:
        return self.family.generate(torch.as_tensor(x, dtype=torch.float64), self.config.num_patterns, self.rows, self.cols, self.config.sharpness)

    def value(self, x: np.ndarray, want_gradient: bool) -> tuple[float, np.ndarray | None]:
        values = torch.as_tensor(x, dtype=torch.float64).requires_grad_(want_gradient)
        patterns = self.family.generate(values, self.config.num_patterns, self.rows, self.cols, self.config.sharpness).float()
        errors = []
        for index, (pixels, columns) in enumerate(zip(self.scenes, self.columns)):
            generator = torch.Generator().manual_seed(self.config.seed * 1000 + index)
            capture = capture_scene(pixels, patterns, self.config.noise_scale, "auto", generator, columns)
            normal, _ = solve_ps_unrolled(capture.captures, capture.emission, pixels.points[columns], pixels.lights(), pixels.rig.falloff)
            cosine = (normal * pixels.normal[columns]).sum(-1).clamp(-1 + 1e-6, 1 - 1e-6)
            errors.append(torch.rad2deg(torch.acos(cosine)).mean())
        mean = torch.stack(errors).mean()
        gradient = None
        if want_gradient:
            mean.backward()
            gradient = np.nan_to_num(values.grad.numpy())
        return float(mean.detach()), gradient

    def __call__(self, x, grad):
        value, gradient = self.value(np.array(x, dtype=np.float64), grad.size > 0)
        if grad.size > 0:
            grad[:] = gradient
        self.trace.append((np.array(x, dtype=np.float64), value))
        if value < self.best_value:
            self.best_x, self.best_value = np.array(x, dtype=np.float64), value
        self.bar.update(1)
        self.bar.set_postfix(best=f"{self.best_value:.2f}")
        return value


def run_search(config: SearchConfig, out: Path, progress: bool = True) -> dict:
    """Search, then write the best patterns to ``out``, ``<stem>.trace.csv`` and ``<stem>.trace.png``."""
    out = Path(out)
    rig = load_rig(config.rig)
    family = get_family(config.family)
    family.check(config.num_patterns, rig.rows, rig.cols)
    scenes = [scene_pixels(scene, rig, require_normals=True) for scene in resolve_scenes(config.scenes, "train", rig)]
    parameters = family.parameters(config.num_patterns, rig.rows, rig.cols)
    low, high = family.bounds(config.num_patterns, rig.rows, rig.cols)
    start = np.clip(np.array([p.default for p in parameters], dtype=np.float64), low, high)
    objective = _Objective(config, scenes, rig.rows, rig.cols, progress)
    optimiser = nlopt.opt(getattr(nlopt, config.algorithm), len(parameters))
    nlopt.srand(config.seed)
    optimiser.set_lower_bounds(low)
    optimiser.set_upper_bounds(high)
    optimiser.set_min_objective(objective)
    optimiser.set_maxeval(config.maxeval)
    optimiser.set_xtol_rel(config.xtol_rel)
    if config.maxtime > 0:
        optimiser.set_maxtime(config.maxtime)
    began = time.perf_counter()
    try:
        optimiser.optimize(start)
        stop_reason = f"nlopt result {optimiser.last_optimize_result()}"
    except (nlopt.RoundoffLimited, nlopt.ForcedStop, RuntimeError, ValueError) as err:
        # NLopt raises on round-off instead of returning; the best point seen is still valid.
        stop_reason = f"stopped by {type(err).__name__}"
    objective.bar.close()
    if objective.best_x is None:
        raise InputError(f"search {config.family}/{config.algorithm} made no evaluation")
    best = objective.patterns(objective.best_x).detach().float().numpy()
    summary = {
        "family": config.family,
        "M": config.num_patterns,
        "algorithm": config.algorithm,
        "evaluations": len(objective.trace),
        "start_mae": objective.trace[0][1],
        "best_mae": objective.best_value,
        "seconds": time.perf_counter() - began,
        "stop": stop_reason,
        "parameters": {p.name: float(v) for p, v in zip(parameters, objective.best_x)},
        "made_by": "displex search",
        "objective": "mean angular error (deg), fixed pixels and noise, unrolled solver",
        "sharpness": config.sharpness,
    }
    save_patterns(out, best, summary)
    _write_trace(out, parameters, objective.trace, summary)
    return summary


def _write_trace(out: Path, parameters, trace, summary) -> None:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["index", *[p.name for p in parameters], "mae", "best_so_far"])
    best = float("inf")
    bests = []
    for index, (x, value) in enumerate(trace):
        best = min(best, value)
        bests.append(best)
        writer.writerow([index, *[f"{v:.6g}" for v in x], f"{value:.6f}", f"{best:.6f}"])
    write_text(out.with_name(out.stem + ".trace.csv"), buffer.getvalue())
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    ax.plot([value for _, value in trace], ".", label="evaluation")
    ax.plot(bests, "-", label="best so far")
    ax.set_xlabel("evaluation")
    ax.set_ylabel("mean angular error (deg)")
    ax.set_title(f"NLopt {summary['algorithm']} on {summary['family']} M={summary['M']}")
    ax.legend()
    fig.text(0.5, 0.005, f"start {summary['start_mae']:.2f} deg, best {summary['best_mae']:.2f} deg; fixed pixels and noise on the training scenes.", ha="center", fontsize=8)
    save_figure(fig, out.with_name(out.stem + ".trace.png"))
