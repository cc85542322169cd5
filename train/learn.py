"""End-to-end pattern learning (`displex train`).

Patterns are unconstrained logits mapped to [0, 1] by a sigmoid. Each step samples pixels from every
training scene, simulates their captures (display model, noise by reparameterisation, clipping,
quantisation; auto exposure per scene recomputed without gradient over a fixed random sample of
at most ``EXPOSURE_PIXELS`` of its pixels, i.e. every pixel of scenes up to that size), reconstructs normals with the
analytic photometric stereo (the fixed-iteration ``solve_ps_unrolled``; validation uses the full
solver), and descends the mean angular error (by default with each pixel's angle capped, see
``TrainConfig.angle_cap_deg``) with Adam under a cosine schedule.
Every random draw of step s comes from a generator seeded by (seed, s), so a run resumed from a
checkpoint continues exactly as an uninterrupted one.

Without a gradient through auto exposure, a step sees a brighter pattern set's gain in signal over
noise but not the shorter exposure that takes most of it back. The search's gradient has that path
(``train.capture.exposure_with_gradient``); learning with it was measured worse on the default
scenes (held-out MAE, ``displex evaluate --noise default``, seeds 0 and 1: M = 4 9.65 / 9.79
against 9.60 / 9.54, M = 2 10.59 / 10.70 against 10.18 / 10.04), so learning keeps the constant.
"""
from __future__ import annotations

import dataclasses
import math
import tempfile
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from capture_sim.atomic import atomic_path, check_folder_place, exclusive_output, refuse_folder_clashes, staged_files, write_json
from capture_sim.errors import InputError, all_finite, check_seed, one_line
from capture_sim.rig import DEFAULT_RIG, check_noise_scale, load_rig, rig_file, rig_source
from capture_sim.scene import file_fingerprints, scene_paths
from patterns.families import FAMILIES, get_family, make_patterns
from patterns.io import check_patterns_match_rig, load_patterns, names_pattern_file, save_patterns
from patterns.parameterization import keep_movable, logits_to_patterns, patterns_to_logits
from reconstruct.photometric_stereo import solve_ps
from reconstruct.unrolled_ps import UnrolledPSConfig, solve_ps_unrolled
from train.capture import capture_scene, scene_exposure
from train.config_io import changed_keys, config_to_dict
from train.evaluate import EvalSettings, evaluate_scene, mean_mae
from train.scene_pixels import ScenePixels, ShuffledPixels, scene_pixels, shuffle_pixels
from train.rerender import rerender_loss
from train.scene_sets import configured_scene_size, resolve_scenes

EXPOSURE_PIXELS = 16384
"""Auto exposure during learning reads at most this many of a scene's pixels (a fixed uniform random
sample; all of them in smaller scenes, such as every default scene). On a 512 x 612 frame
(``train.bench.full_frame_pixels``) the sample's exposure was within 0.12% of the whole frame's
for four pattern sets (M = 2 and 4; 65536 pixels: 0.02%), and it saves 95% of the full-frame
contraction every step."""
LOSSES = ("capped_angular", "angular", "cosine")
DEFAULT_ANGLE_CAP_DEG = 40.0
SOLVERS = ("full", "unrolled")


MAX_LEARNING_RATE = 1e30
"""Largest ``learning_rate`` accepted: far beyond any useful one (1 is the default), and below the
values (about 1e38) at which Adam's float32 step overflows."""


@dataclass(frozen=True)
class TrainConfig:
    """Settings of one pattern-learning run (TOML files in configs/train/)."""

    num_patterns: int = 4
    """M, the number of patterns to learn."""
    init: str = "auto"
    """Starting patterns: a family name (made with its default parameters), a pattern file, or
    'auto': tri_complementary for M <= 2 (mono families are rank-deficient there), else
    mono_gradient. Measured on the default scenes (test MAE after the default 150 steps): at M = 2,
    10.84 deg from tri_complementary, 11.20 from tri_gradient, 12.07 from tri_random; at M = 4,
    9.45 from mono_gradient, 9.59 from tri_complementary."""
    steps: int = 150
    """Adam steps (on the default scenes the test MAE stops improving after about 100 at lr 1)."""
    learning_rate: float = 1.0
    """Initial Adam step size on the logits. Large because the starting families hold values at
    the sigmoid's clamp (logits near +-6.9) that must move several units; 0.1 and 0.3 learned
    less in the same steps and 3.0 overshot (test MAE at M = 4: 9.92 at 0.1/60 steps, 9.78 at
    0.3/100, 9.51 at 1.0/100, 10.02 at 3.0/100)."""
    final_lr_fraction: float = 0.05
    """The cosine schedule decays the step size to this fraction of ``learning_rate``."""
    pixels_per_scene: int = 2048
    """Pixels sampled from every training scene at each step."""
    noise_scale: float = 1.0
    """Multiplier of the rig's noise variances during training (0 = noise-free)."""
    loss: str = "capped_angular"
    """'capped_angular' (mean angle in radians, each pixel's at most ``angle_cap_deg``), 'angular'
    (mean angle) or 'cosine' (mean 1 - cos)."""
    angle_cap_deg: float = DEFAULT_ANGLE_CAP_DEG
    """Per-pixel cap of the 'capped_angular' loss, degrees. A pixel beyond it (a specular highlight
    or cast shadow the Lambertian solver cannot fit whatever the patterns) adds a constant and no
    gradient, so learning spends the patterns on pixels it can fix. On the demo scenes it learned
    M = 2 patterns with held-out MAE 10.20 / 10.12 / 10.09 deg (seeds 0 / 1 / 2) against 10.41 /
    10.54 / 10.79 uncapped, and M = 4 ones as good (9.60 / 9.51 against 9.58 / 9.53); a 30 deg
    cap learned as 40 (10.20 at M = 2, seed 0). Caps below ~0.08 deg (the loss's clamp of the
    cosine) give no gradient at all."""
    scenes: tuple[str, ...] = ()
    """Training scene files or folders; empty = the default synthetic training split."""
    val_scenes: tuple[str, ...] = ()
    """Validation scenes (logged only, never used to pick patterns); empty = the default synthetic
    test split when training on the default scenes, and no validation when ``scenes`` are given."""
    scene_size: tuple[int, int] | None = None
    """Image size (height, width) of the default synthetic scenes; None (unset) is replaced on
    construction by a quarter of the rig camera's resolution (``capture_sim.synth.default_scene_size``:
    128 x 153 on the reference rig)."""
    scene_seed: int = 0
    """Seed of the default synthetic scenes."""
    rig: str = DEFAULT_RIG
    """Rig preset or TOML path."""
    seed: int = 0
    """Seed of initial random patterns, pixel sampling and noise."""
    val_every: int = 50
    """Validate (full held-out scenes) every this many steps and at the end; 0 = only at the end."""
    checkpoint_every: int = 25
    """Write a resumable checkpoint every this many steps."""
    solver: str = "unrolled"
    """Reconstruction inside the training loss: 'unrolled' (``solve_ps_unrolled``) or 'full'
    (``solve_ps``, the evaluation solver with restarts and exact implicit gradients). 'full' costs
    about 5x more per step and, on the default scenes, learned no better patterns in the same
    time (it differs from 'unrolled' mostly on specular pixels that no pattern fixes)."""
    rerender_weight: float = 0.0
    """Weight of the re-rendering loss (estimated normals and albedo rendered as Lambertian under
    the patterns by ``capture_sim.render.render_olat``, against the simulated captures); 0 =
    normal loss only."""

    def __post_init__(self):
        for name, least in (("num_patterns", 1), ("pixels_per_scene", 1), ("steps", 0)):
            if getattr(self, name) < least:
                raise InputError(f"{name} must be >= {least}, got {getattr(self, name)}")
        object.__setattr__(self, "scene_size", configured_scene_size(self.scene_size, self.rig))
        if self.solver not in SOLVERS:
            raise InputError(f"solver must be one of {', '.join(SOLVERS)}, got {self.solver!r}")
        if self.loss not in LOSSES:
            raise InputError(f"loss must be one of {', '.join(LOSSES)}, got {self.loss!r}")
        # A NaN cap whatever the loss: normal_loss refuses it at the first step, after the scenes are read.
        if (self.loss == "capped_angular" and not self.angle_cap_deg > 0) or math.isnan(self.angle_cap_deg):
            raise InputError(f"angle_cap_deg must be > 0 (inf for no cap), got {self.angle_cap_deg!r}")
        # Adam's step (learning rate over its bias correction) must stay a float32 number.
        if not 0 < self.learning_rate <= MAX_LEARNING_RATE:
            raise InputError(f"learning_rate must be a number in (0, {MAX_LEARNING_RATE:g}], got {self.learning_rate!r}")
        if not 0 < self.final_lr_fraction <= 1:
            raise InputError(f"final_lr_fraction must lie in (0, 1], got {self.final_lr_fraction!r}")
        check_noise_scale("noise_scale", self.noise_scale)
        if not 0 <= self.rerender_weight < math.inf:
            raise InputError(f"rerender_weight must be a finite number >= 0, got {self.rerender_weight!r}")
        if self.checkpoint_every < 1:
            raise InputError(f"checkpoint_every must be >= 1, got {self.checkpoint_every}")
        if self.val_every < 0:
            raise InputError(f"val_every must be >= 0 (0 = only at the end), got {self.val_every}")
        check_seed("seed", self.seed)
        check_seed("scene_seed", self.scene_seed)
        if self.init != "auto" and self.init not in FAMILIES and not names_pattern_file(self.init):
            raise InputError(f"init must be 'auto', a family ({', '.join(FAMILIES)}) or a pattern file, got {self.init!r}")


def auto_init_family(num_patterns: int) -> str:
    """The family ``init = 'auto'`` starts M patterns from (see ``TrainConfig.init``)."""
    return "tri_complementary" if num_patterns <= 2 else "mono_gradient"


def initial_patterns(config: TrainConfig, rows: int, cols: int) -> torch.Tensor:
    """(M, R, C, 3) starting patterns from a family name, 'auto' or a pattern file."""
    if config.init == "auto":
        family = auto_init_family(config.num_patterns)
        if not get_family(family).supports(config.num_patterns, rows, cols):
            raise InputError(f"init 'auto' starts M = {config.num_patterns} from {family}, which does not support it on a "
                             f"{rows} x {cols} grid; set init to a family that does (train's --init, or init in the config's learning settings; "
                             f"see displex patterns list --M {config.num_patterns})")
        return make_patterns(family, config.num_patterns, rows=rows, cols=cols, seed=config.seed).float()
    if config.init in FAMILIES:
        return make_patterns(config.init, config.num_patterns, rows=rows, cols=cols, seed=config.seed).float()
    path = Path(config.init)
    if not names_pattern_file(config.init):
        raise InputError(f"--init must be a family ({', '.join(FAMILIES)}) or a pattern file, got {config.init!r}")
    values, _ = load_patterns(path)
    check_patterns_match_rig(values, rows, cols, config.rig, path)
    if values.shape[0] != config.num_patterns:
        raise InputError(f"{path} holds {values.shape[0]} patterns but M = {config.num_patterns} (learn M = {values.shape[0]} patterns to start from it)")
    return torch.as_tensor(values)


def normal_loss(estimate: torch.Tensor, truth: torch.Tensor, kind: str, angle_cap_deg: float = DEFAULT_ANGLE_CAP_DEG) -> torch.Tensor:
    """Mean error between (N, 3) unit normals: 'angular' (radians), 'capped_angular' (radians,
    each pixel's angle at most ``angle_cap_deg`` degrees) or 'cosine' (1 - cos); a 0-d tensor.

    Raises:
        InputError: an unknown ``kind``, shapes that are not the same (N, 3) with N >= 1, or a NaN
            cap. (The values are not scanned: a hot path of learning, fed by the solvers.)
    """
    if kind not in LOSSES:
        raise InputError(f"loss must be one of {', '.join(LOSSES)}, got {kind!r}")
    estimate, truth = torch.as_tensor(estimate), torch.as_tensor(truth)
    if estimate.dim() != 2 or estimate.shape[-1] != 3 or estimate.shape != truth.shape or estimate.shape[0] == 0:
        raise InputError(f"normal_loss needs two (N, 3) normal arrays with N >= 1, got {tuple(estimate.shape)} and {tuple(truth.shape)}")
    if math.isnan(angle_cap_deg):
        raise InputError("angle_cap_deg must be a number of degrees, got nan")
    cosine = (estimate * truth).sum(-1)
    if kind == "cosine":
        return (1.0 - cosine).mean()
    # acos has an infinite slope at 1: clamp just inside so that exact pixels give finite gradients.
    angle = torch.acos(cosine.clamp(-1.0 + 1e-6, 1.0 - 1e-6))
    if kind == "capped_angular":  # a cap of 180 degrees or more caps nothing (and may not fit float32)
        angle = angle.clamp_max(math.radians(min(angle_cap_deg, 180.0)))
    return angle.mean()


def step_generator(seed: int, step: int) -> torch.Generator:
    """The random generator of one training step (independent of where a run was resumed)."""
    return torch.Generator().manual_seed(seed * 1_000_003 + step)


def training_samplers(scenes: Iterable[ScenePixels], config: TrainConfig) -> list[ShuffledPixels]:
    """Each training scene's pixels shuffled once, in an order fixed by (seed, scene position).

    ``scenes`` may be an iterator (``prepared_scenes``): each scene's unshuffled pixels are then
    released once its shuffled copy is made, instead of every scene being held twice."""
    samplers = []
    # Not enumerate: its reused result tuple would hold the last scene while the next is prepared.
    for pixels in scenes:
        state = int(np.random.SeedSequence([config.seed, 1, len(samplers)]).generate_state(1)[0])
        samplers.append(shuffle_pixels(pixels, config.pixels_per_scene, torch.Generator().manual_seed(state)))
        del pixels  # before the next scene is prepared
    return samplers


def prepared_scenes(scenes: list, rig) -> Iterator[ScenePixels]:
    """``scene_pixels`` of each scene of ``scenes`` (a list it empties as it goes, so that a loaded
    scene's arrays are released once its pixels are prepared)."""
    while scenes:
        yield scene_pixels(scenes.pop(0), rig, require_normals=True)


def training_loss(logits: torch.Tensor, scenes: list[ShuffledPixels], config: TrainConfig, step: int, ps_config: UnrolledPSConfig,
                  parts: dict | None = None) -> torch.Tensor:
    """Loss of one step: a random window of every scene's shuffled pixels, simulated, reconstructed,
    compared; every scene weighs the same. With the re-rendering loss, ``parts`` (a dict, if
    given) receives the scene means of its two terms as floats: ``normal`` and ``rerender``
    (unweighted)."""
    generator = step_generator(config.seed, step)
    patterns = logits_to_patterns(logits)
    draws = []
    for sampler in scenes:
        part = sampler.draw(generator)
        exposure = scene_exposure(sampler.every_pixel(EXPOSURE_PIXELS), patterns)
        draws.append((sampler, part, capture_scene(sampler.scene, patterns, config.noise_scale, exposure, generator, part)))
    losses, terms = [], []
    for (sampler, part, capture), (normal, albedo) in zip(draws, reconstruct_draws(draws, config.solver, ps_config)):
        pixels = sampler.scene
        loss = normal_loss(normal, pixels.normal[part], config.loss, config.angle_cap_deg)
        if config.rerender_weight > 0:
            rendered = rerender_loss(normal, albedo, capture, pixels, part)
            if parts is not None:
                terms.append((float(loss.detach()), float(rendered.detach())))
            loss = loss + config.rerender_weight * rendered
        losses.append(loss)
    if parts is not None and terms:
        parts.update(normal=float(np.mean([t[0] for t in terms])), rerender=float(np.mean([t[1] for t in terms])))
    return torch.stack(losses).mean()


def reconstruct_draws(draws: list, solver: str, ps_config: UnrolledPSConfig) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Normals and albedo of the sampled pixels of several scenes, one solve per group of scenes
    that share lights and falloff (a few wide operations instead of many small ones).

    Scenes are captured at different exposures, but both solvers are invariant to the scale of the
    emission (their damping is relative): solving a group with its first scene's emission gives
    every scene's normals exactly, and albedo scaled by that emission's exposure over the scene's.

    Args:
        draws: (sampler, part, capture) per scene: a ShuffledPixels, the slice of its window and
            the Capture of those pixels.
        solver: "unrolled" or "full" (``TrainConfig.solver``).
        ps_config: settings of the unrolled solver.

    Returns:
        [(normal (P, 3), albedo (P, 3))] per draw, differentiable like the solvers' outputs.
    """
    groups: dict[tuple, list[int]] = {}
    for index, (sampler, _, _) in enumerate(draws):
        key = (sampler.scene.rig.falloff, tuple(sampler.scene.lights().reshape(-1).tolist()))
        groups.setdefault(key, []).append(index)
    solved: list = [None] * len(draws)
    for members in groups.values():
        first_sampler, _, first_capture = draws[members[0]]
        pixels = first_sampler.scene
        captures = torch.cat([draws[i][2].captures for i in members], dim=1)
        points = torch.cat([draws[i][0].scene.points[draws[i][1]] for i in members])
        if solver == "full":
            result = solve_ps(captures, first_capture.emission, points, pixels.lights(), pixels.rig.falloff)
            normal, albedo = result.normal, result.albedo
        else:
            reach = torch.cat([draws[i][0].reach[:, draws[i][1]].T for i in members]).T  # pixel-major, as stored
            normal, albedo = solve_ps_unrolled(captures, first_capture.emission, points, pixels.lights(), pixels.rig.falloff, ps_config, reach=reach)
        sizes = [draws[i][2].captures.shape[1] for i in members]
        for i, scene_normal, scene_albedo in zip(members, normal.split(sizes), albedo.split(sizes)):
            solved[i] = (scene_normal, scene_albedo * (first_capture.exposure / draws[i][2].exposure))
    return solved


def cosine_schedule(config: TrainConfig):
    """Learning-rate multiplier per step: cosine from 1 down to ``final_lr_fraction``."""
    floor = config.final_lr_fraction

    def factor(step: int) -> float:
        progress = min(1.0, step / max(1, config.steps))
        return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * progress))

    return factor


@dataclass(frozen=True, eq=False)
class TrainResult:
    """Learned (M, R, C, 3) patterns, the validation MAE history [(step, degrees)], the final loss,
    and the wall seconds the run took, summed over the sessions of a resumed run (each
    interrupted session counted up to its last checkpoint)."""

    patterns: np.ndarray
    val_history: list
    final_loss: float
    seconds: float


def checkpoint_path(out: Path) -> Path:
    return out.with_name(out.stem + ".ckpt.pt")


def config_record_path(out: Path) -> Path:
    """``<out stem>.config.json``: the resolved config written next to a pattern file."""
    return out.with_name(out.stem + ".config.json")


def output_files(out: Path) -> list[tuple[str, Path]]:
    """(what, path) of the files a run writing patterns to ``out`` leaves next to them."""
    return [("--out", out), ("config record", config_record_path(out))]


CHECKPOINT_KEYS = ("config", "logits", "optimiser", "scheduler", "step", "val_history")


def checkpoint_identity(config: TrainConfig) -> dict:
    """The config as a checkpoint records and compares it: ``config_to_dict`` with the scene,
    pattern and rig files as absolute paths, so that a run resumes whether its files are named
    relative to the working directory or absolutely, and a relative name that means other files
    from another directory does not resume (the config record beside the patterns keeps the
    names as given); plus ``input_files`` (``input_fingerprints``), so that a run does not resume
    on, or report validation of, files rewritten since. The files must exist."""
    def absolute(name: str) -> str:
        return str(Path(name).resolve())

    identity = config_to_dict(dataclasses.replace(
        config,
        scenes=tuple(absolute(name) for name in config.scenes),
        val_scenes=tuple(absolute(name) for name in config.val_scenes),
        init=absolute(config.init) if names_pattern_file(config.init) else config.init,
        rig=absolute(config.rig) if rig_file(config.rig) else config.rig,
    ))
    identity["input_files"] = input_fingerprints(config)
    return identity


def input_fingerprints(config) -> list[list]:
    """``file_fingerprints`` of every file a learning or search config (``TrainConfig`` or
    ``train.search.SearchConfig``) reads: its scene files, an init pattern file, and the rig's
    TOML file (a preset's too). A run made from files rewritten since is neither resumed nor
    reused (``train.compare_methods``)."""
    init = getattr(config, "init", "")
    init_file = [init] if names_pattern_file(init) else []
    scenes = (*config.scenes, *getattr(config, "val_scenes", ()))
    return file_fingerprints([*scene_paths(scenes), *init_file, rig_source(config.rig)])


_AFRESH = "pass --fresh (or delete it) to start afresh"


def load_checkpoint(checkpoint: Path, resolved: dict) -> dict:
    """The training state saved in ``checkpoint`` by a run with the config ``resolved``
    (``checkpoint_identity`` of the run's config).

    Loaded with ``weights_only`` (tensors and plain containers; a checkpoint never runs code).

    Raises:
        InputError: the file is unreadable or incomplete (e.g. truncated), or was written with
            another config; the message says to delete it to start afresh.
    """
    try:
        state = torch.load(checkpoint, weights_only=True)
    except Exception:  # a damaged file fails in the zip reader or the unpickler, in many ways
        raise InputError(f"checkpoint {checkpoint} is damaged or not a torch checkpoint; {_AFRESH}") from None
    if not isinstance(state, dict) or not all(key in state for key in CHECKPOINT_KEYS):
        raise InputError(f"checkpoint {checkpoint} is not a displex training checkpoint; {_AFRESH}")
    if state["config"] != resolved:
        changed = changed_keys(state["config"], resolved)
        if changed == ["input_files"]:
            files = changed_files(state["config"]["input_files"], resolved["input_files"])
            raise InputError(f"checkpoint {checkpoint} was made from input files (scenes, start patterns, rig) that were rewritten, "
                             f"replaced or touched since{files}; {_AFRESH}")
        raise InputError(f"checkpoint {checkpoint} was written with another config ({', '.join(changed) or 'other keys'} differ); {_AFRESH}")
    return state


def changed_files(recorded, current: list[list]) -> str:
    """' (a, b)': the names of the files whose ``file_fingerprints`` differ between a run's record
    and now, or '' when the record cannot be read as fingerprints."""
    try:
        before = {entry[0]: list(entry) for entry in recorded}
    except (TypeError, IndexError, KeyError):
        return ""
    now = {entry[0]: entry for entry in current}
    names = [Path(path).name for path in sorted(set(before) | set(now)) if before.get(path) != now.get(path)]
    return f" ({', '.join(names)})" if names else ""


def check_state_fits(state: dict, logits: torch.Tensor, checkpoint: Path) -> None:
    """Refuse (``InputError``) a checkpoint whose config matched but whose patterns or Adam state
    do not fit the run's ``logits``: other shapes or non-finite values (an edited or corrupted
    file; Adam's ``load_state_dict`` checks neither, and its first step would fail or write NaN)."""

    def fits(value) -> bool:
        return isinstance(value, torch.Tensor) and value.shape == logits.shape and all_finite(value)

    def usable_moment(value) -> bool:  # Adam's per-parameter tensors, and its step count (a scalar)
        if not isinstance(value, torch.Tensor):
            return True
        return fits(value) if value.dim() else all_finite(value)

    if not fits(state["logits"]):
        raise InputError(f"checkpoint {checkpoint} is damaged: its patterns do not fit its config; {_AFRESH}")
    try:
        usable = all(map(usable_moment, state["optimiser"]["state"].get(0, {}).values()))
    except (KeyError, TypeError, AttributeError):
        usable = False
    if not usable:
        raise InputError(f"checkpoint {checkpoint} is damaged: its optimiser state does not fit its config; {_AFRESH}")


CHECKPOINT_MODES = ("resume", "fresh", "resume_or_fresh")


def train_patterns(config: TrainConfig, out: Path, logdir: Path | None = None, progress: bool = True,
                   checkpoint_mode: str = "resume", own_logdir: bool = False) -> TrainResult:
    """Learn patterns, write them to ``out`` (.npz) with the resolved config beside them.

    The run checkpoints to ``<out stem>.ckpt.pt``. ``checkpoint_mode`` says what to do with an
    existing one: 'resume' resumes it if it was written with the same config and refuses any other
    (``InputError``: the user decides); 'fresh' deletes it first; 'resume_or_fresh' resumes a
    matching one and replaces any other (for callers that own the output folder, e.g. compare,
    where a checkpoint of another config is left over from an interrupted run of an older config).
    A resumed run hides the TensorBoard events of the steps it redoes; with ``own_logdir`` (the
    folder holds this output's runs alone, e.g. compare's), a fresh run hides every earlier event
    there, which other runs sharing a folder must keep.
    """
    if checkpoint_mode not in CHECKPOINT_MODES:
        raise InputError(f"checkpoint_mode must be one of {', '.join(CHECKPOINT_MODES)}, got {checkpoint_mode!r}")
    # A second run on the same output would share its checkpoint and silently replace its result.
    with exclusive_output(out, "training run"):
        return _train(config, Path(out), logdir, progress, checkpoint_mode, own_logdir)


def _train(config: TrainConfig, out: Path, logdir: Path | None, progress: bool, checkpoint_mode: str, own_logdir: bool) -> TrainResult:
    began = time.perf_counter()
    check_logdir(logdir, [*output_files(out), ("checkpoint", checkpoint_path(out))])  # before the scenes, which can take a while
    rig = load_rig(config.rig)
    logits = patterns_to_logits(initial_patterns(config, rig.rows, rig.cols)).detach().requires_grad_()
    optimiser = torch.optim.Adam([logits], lr=config.learning_rate)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimiser, cosine_schedule(config))
    resolved, identity = config_to_dict(config), checkpoint_identity(config)
    start_step, val_history, loss_value, earlier_seconds = 0, [], float("nan"), 0.0
    checkpoint = checkpoint_path(out)
    state = None
    # The checkpoint is read before the scenes: one of another config is refused at once, not
    # after the default scenes are synthesised (--fresh deletes it once they have loaded).
    if checkpoint.exists() and checkpoint_mode != "fresh":
        try:
            state = load_checkpoint(checkpoint, identity)
            check_state_fits(state, logits, checkpoint)
        except InputError:
            if checkpoint_mode == "resume":
                raise
    # One scene at a time: loaded, prepared, shuffled (full-resolution scenes are ~0.5 GB each).
    train_scenes = training_samplers(prepared_scenes(resolve_scenes(config.scenes, "train", rig, config.scene_size, config.scene_seed, separated=False), rig), config)
    # Validating a user's training scenes against the synthetic defaults would report a number about
    # scenes nobody asked for: without val_scenes, only the default training set validates.
    validate = bool(config.val_scenes) or not config.scenes
    val_scenes = [scene_pixels(s, rig, require_normals=True) for s in resolve_scenes(config.val_scenes, "test", rig, config.scene_size, config.scene_seed, separated=False)] if validate else []
    if checkpoint_mode == "fresh" and checkpoint.exists():
        checkpoint.unlink()
    if state is not None:
        with torch.no_grad():
            logits.copy_(state["logits"])
        try:
            optimiser.load_state_dict(state["optimiser"])
            scheduler.load_state_dict(state["scheduler"])
        except (ValueError, KeyError, TypeError, RuntimeError):
            raise InputError(f"checkpoint {checkpoint} is damaged: its optimiser state does not fit its config; {_AFRESH}") from None
        start_step, val_history = state["step"], state["val_history"]
        loss_value = state.get("loss", float("nan"))
        earlier_seconds = state.get("seconds", 0.0)
    # A resumed run hides the steps it redoes (logged from 1); a fresh one hides nothing unless the
    # folder is its own: other runs may share it.
    writer = summary_writer(logdir, start_step + 1 if start_step or own_logdir else None)
    ps_config = UnrolledPSConfig()
    eval_settings = EvalSettings(noise_scale=config.noise_scale, seed=config.seed + 7919)
    bar = tqdm(range(start_step, config.steps), initial=start_step, total=config.steps, desc=f"learning M={config.num_patterns}", disable=not progress, unit="step")
    for step in bar:
        optimiser.zero_grad()
        parts: dict = {}
        # The two terms of a loss with re-rendering go to TensorBoard besides their weighted sum.
        loss = training_loss(logits, train_scenes, config, step, ps_config,
                             **({"parts": parts} if writer is not None and config.rerender_weight > 0 else {}))
        loss.backward()
        if not (torch.isfinite(loss.detach()) and torch.isfinite(logits.grad).all()):
            # Stop before the step writes NaN into the patterns (and a checkpoint).
            raise InputError(f"learning diverged at step {step + 1}: the loss or its gradient is not finite "
                             f"(loss {float(loss.detach()):.4g}); lower learning_rate or rerender_weight")
        optimiser.step()
        keep_movable(logits)
        rate = scheduler.get_last_lr()[0]  # the rate this step used (the scheduler's next one after its step)
        scheduler.step()
        loss_value = float(loss.detach())
        done = step + 1
        if writer is not None:
            writer.add_scalar("train/loss", loss_value, done)
            writer.add_scalar("train/learning_rate", rate, done)
            for name, value in parts.items():
                writer.add_scalar(f"train/{name}_loss", value, done)
        if val_scenes and ((config.val_every and done % config.val_every == 0) or done == config.steps):
            val_history.append((done, _validate(logits, val_scenes, eval_settings, writer, done)))
        bar.set_postfix(loss=f"{loss_value:.4f}", **({"val_mae": f"{val_history[-1][1]:.2f}"} if val_history else {}))
        if done % config.checkpoint_every == 0 or done == config.steps:
            state = {"config": identity, "logits": logits.detach().clone(), "optimiser": optimiser.state_dict(), "scheduler": scheduler.state_dict(), "step": done, "val_history": val_history, "loss": loss_value,
                     "seconds": earlier_seconds + time.perf_counter() - began}
            with atomic_path(checkpoint, suffix=".pt", sync=True) as tmp:
                try:
                    torch.save(state, tmp)
                except RuntimeError as err:  # torch's zip writer reports a failed write (a full disk) so
                    raise InputError(f"cannot write checkpoint {checkpoint}: {err} (is the disk full?)") from None
    if val_scenes and not val_history:  # no step ran (steps = 0): validate the start patterns
        val_history.append((start_step, _validate(logits, val_scenes, eval_settings, writer, start_step)))
    if writer is not None:
        writer.close()
    learned = logits_to_patterns(logits.detach()).numpy().astype(np.float32)
    meta = {
        "family": "learned",
        "init": config.init,
        "made_by": "displex train",
        "rig": rig.name,
        "config": resolved,
        "val_mae_history": val_history,
        "final_train_loss": loss_value if math.isfinite(loss_value) else None,
    }
    # The pattern file and its config record land together (the pattern file last): a stop
    # between two separate writes left a new pattern file beside an earlier run's record.
    with staged_files(out.parent, last=(out.name,)) as staging:
        save_patterns(staging / out.name, learned, meta)
        write_json(staging / config_record_path(out).name, resolved)
    return TrainResult(learned, val_history, loss_value, earlier_seconds + time.perf_counter() - began)


def summary_writer(logdir: Path | None, first_new_step: int | None = None):
    """A TensorBoard writer for the folder ``logdir`` (created if needed), or None without one.
    With ``first_new_step``, the events an earlier run logged in the folder at that step and later
    are hidden, whichever run logged them: this run logs them again (a resumed learning run). It may
    wait up to 1 s so that its event file sorts after the folder's earlier ones."""
    name = check_logdir(logdir)
    if name is None:
        return None
    from torch.utils.tensorboard import SummaryWriter

    _wait_for_a_later_event_file_name(Path(name))
    return SummaryWriter(name, purge_step=first_new_step)


def _wait_for_a_later_event_file_name(folder: Path) -> None:
    """Sleep into the next second if an event file in ``folder`` was created in this one.

    TensorBoard reads a folder's event files in name order, and a resumed run's purge of the
    steps it logs again holds only for files read before its own. A name is the creation second
    followed by host, process id and a per-process counter, so two writers of one second can sort
    out of order (counter 10 sorts before 9). A later second always sorts after.
    """
    seconds = [int(part[3]) for part in (path.name.split(".") for path in folder.glob("events.out.tfevents.*"))
               if len(part) > 3 and part[3].isdigit()]
    now = time.time()
    if seconds and max(seconds) == int(now):
        time.sleep(1.0 - now % 1.0 + 0.01)


def check_logdir(logdir: Path | None, outputs=()) -> str | None:
    """Create the TensorBoard folder ``logdir`` and check that it takes files, before any work
    (``InputError`` otherwise, also if one of the run's ``outputs``, (what, path) pairs of the
    files it writes, is that folder or would have to hold it); its name for the writer, or None
    without one."""
    if logdir is None:
        return None
    name = tensorboard_folder_name(logdir, "--logdir")
    if Path(logdir).exists() and not Path(logdir).is_dir():
        raise InputError(f"--logdir {logdir} is a file, not a folder")
    refuse_folder_clashes(outputs, [("--logdir", logdir)])  # an output there would fail after the work
    check_folder_place(Path(logdir), f"--logdir {logdir} is not writable")  # a broken link on the way says so
    # The writer writes from a background thread, where a failure would print a thread traceback:
    # try the folder here first.
    try:
        Path(logdir).mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=logdir).close()
    except OSError as err:
        raise InputError(f"--logdir {logdir} is not writable: {err.strerror or err}") from None
    return name


def tensorboard_folder_name(folder: Path, what: str) -> str:
    """``folder`` as the text TensorBoard's writer takes; ``InputError`` naming ``what`` (the option
    the user set, e.g. ``--logdir``) for a name that is not valid UTF-8 (the writer fails on it from
    inside its own thread)."""
    name = str(folder)
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        raise InputError(f"{what} {one_line(name)}: its TensorBoard logs need a folder name that is valid UTF-8; choose another") from None
    return name


def _validate(logits: torch.Tensor, scenes: list[ScenePixels], settings: EvalSettings, writer, step: int) -> float:
    patterns = logits_to_patterns(logits.detach())
    evaluations = [evaluate_scene(pixels, patterns, settings, index) for index, pixels in enumerate(scenes)]
    value = mean_mae(evaluations)
    if writer is not None:
        writer.add_scalar("val/mae_deg", value, step)
        # Patterns as an image strip: (3, R, M * C).
        strip = torch.cat(list(patterns), dim=1).permute(2, 0, 1)
        writer.add_image("patterns", strip, step)
        first = scenes[0]
        normal_image = first.transport.to_image(evaluations[0].result.normal[None], fill=0.0)[0]
        writer.add_image("val/normal_estimate", (0.5 * (normal_image + 1)).clamp(0, 1).permute(2, 0, 1), step)
    return value
