"""`displex invrender`: inverse rendering of one scene, relighting evaluation, model selection, outputs.

Data (all from the scene's OLAT stack O, DESIGN sections 3 and 4):
- lights are split 5:1 into fit and held-out test lights (every ``TEST_EVERY``-th held out) (``reconstruct.relight.split_lights``);
- OLAT exposure e_olat is auto exposure over all K noise-free OLAT images of the mask; the
  held-out truth is e_olat * O[test] (noise-free), and relit images use the same e_olat;
- ``patterns = "olat"``: the fit captures are the fit lights' OLAT images, noisy (rig model)
  unless ``noise = "off"``, with one-hot emission e_olat;
- a pattern file: the fit captures are simulated captures of the patterns (``simulate``, backlight
  and gamma included, exposure auto unless fixed, noise as above).
Model selection (``basis = "auto"``) validates on noisy OLAT images of every ``VALIDATION_EVERY``-th fit light (5th); in
OLAT mode its candidates are fitted on the other fit lights, in pattern mode on the pattern
captures (at a rig, the validation images are a few extra OLAT captures). The test lights are
never used for any decision.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from tqdm import tqdm

from capture_sim.atomic import staged_files, write_json
from capture_sim.errors import DisplexWarning, InputError, check_field_types, check_seed, check_thread_count
from capture_sim.rig import DEFAULT_RIG, load_rig
from capture_sim.scene import load_scene, rig_for_scene
from capture_sim.simulator import auto_exposure, sensor, simulate
from patterns.io import check_patterns_match_rig, load_patterns
from reconstruct.inverse_render import EMISSION_RANGE, FitConfig, FitProblem
from reconstruct.metrics import normal_metrics
from reconstruct.model_selection import SelectionConfig, choose_light_model, light_spread, select_basis
from reconstruct.relight import TEST_EVERY, VALIDATION_EVERY, olat_emission, relighting_metrics, split_lights
from train.invrender_figures import write_outputs
from train.learn import tensorboard_folder_name
from train.scene_pixels import scene_pixels
from train.simulate_command import parse_exposure
from train.torch_threads import torch_threads

GEOMETRY_CHOICES = ("auto", "near", "far")
NOISE_CHOICES = ("default", "off")
MAX_BASIS = 8


@dataclass(frozen=True)
class InvRenderConfig:
    """What `displex invrender` does. The CLI maps its flags onto these fields; geometry, batch_pixels,
    tv_weight and selection are set from Python only."""

    scene: Path
    """Scene interchange .npz (DESIGN section 7) with an OLAT stack."""
    patterns: str = "olat"
    """'olat' (fit the fit-split OLAT images directly) or a pattern file (.npz / .npy)."""
    out: Path | None = None
    """Output folder for arrays, figures, TensorBoard logs and JSON; None writes nothing there."""
    json: Path | None = None
    """Also write the result JSON here."""
    basis: str = "auto"
    """'auto' (model selection, ``reconstruct.model_selection``) or J = 1..8 (specular bases)."""
    iterations: int = 400
    """Adam steps of the final fit."""
    seed: int = 0
    """Seed of the capture noise, k-means and pixel batches."""
    noise: str = "default"
    """'default': the rig's noise model and bit depth on every capture; 'off': noise-free."""
    exposure: str = "rig"
    """Exposure of pattern captures: 'rig' (the rig's setting; auto for the presets), 'auto' or a
    positive number (OLAT captures always use auto)."""
    geometry: str = "auto"
    """'near', 'far' or 'auto' (far field only where it is indistinguishable, ``choose_light_model``)."""
    rig: str = DEFAULT_RIG
    """Rig preset or TOML path: display model, noise and falloff (lights come from the scene)."""
    batch_pixels: int = 8192
    """Pixels per Adam step."""
    tv_weight: float = 1e-3
    """Weight of the normals' total variation (see ``FitConfig.tv_weight``)."""
    threads: int = 0
    """torch intra-op threads while the command runs (restored afterwards); 0 keeps torch's default
    (one per core). The CLI sets it from ``displex --threads T`` (also accepted after ``invrender``).
    On a quiet 2-core machine two threads are faster (the noise-free 128 x 153 OLAT fit: 24 s wall
    with two, 40 s with one); on a busy one pass 1: a fit step is a few hundred small element-wise
    passes, and when the other core is taken every parallel pass waits for a descheduled thread
    (load about 6: 291 s wall with two threads against 42 s with one)."""
    selection: SelectionConfig = field(default_factory=SelectionConfig)
    """Model-selection sweep settings (used when ``basis = 'auto'``)."""

    def num_basis(self) -> int | None:
        """J as an int, or None for 'auto'; raises ``InputError`` for anything else."""
        if str(self.basis) == "auto":
            return None
        try:
            value = int(str(self.basis))
        except ValueError:
            raise InputError(f"--basis must be 'auto' or an integer 1..{MAX_BASIS}, got {self.basis!r}") from None
        if not 1 <= value <= MAX_BASIS:
            raise InputError(f"--basis must be 'auto' or an integer 1..{MAX_BASIS}, got {self.basis!r}")
        return value

    def validate(self) -> None:
        """Raise ``InputError`` with one line for a bad setting."""
        check_thread_count(self.threads)  # first: its message is the one `displex --threads` gives
        check_field_types(self)
        if not isinstance(self.selection, SelectionConfig):
            raise InputError(f"selection must be a SelectionConfig, got {type(self.selection).__name__}")
        self.num_basis()
        if self.iterations < 1:
            raise InputError(f"--iterations must be at least 1, got {self.iterations}")
        if self.noise not in NOISE_CHOICES:
            raise InputError(f"noise must be one of {', '.join(NOISE_CHOICES)}, got {self.noise!r}")
        if self.geometry not in GEOMETRY_CHOICES:
            raise InputError(f"geometry must be one of {', '.join(GEOMETRY_CHOICES)}, got {self.geometry!r}")
        if self.batch_pixels < 1 or not 0 <= self.tv_weight < math.inf:
            raise InputError("batch_pixels must be positive and tv_weight non-negative and finite")
        check_seed("--seed", self.seed)
        parse_exposure(str(self.exposure))
        if self.patterns == "olat" and str(self.exposure) not in ("rig", "auto"):
            raise InputError(f"--exposure {self.exposure} applies to pattern captures; OLAT captures are always auto-exposed (drop it or pass --patterns)")

    def to_dict(self) -> dict:
        values = asdict(self)
        for key in ("scene", "out", "json"):
            values[key] = None if values[key] is None else str(values[key])
        return values


def normal_error_stats(estimate: torch.Tensor, truth: torch.Tensor) -> dict:
    """``reconstruct.metrics.normal_metrics`` of (N, 3) normals over all N pixels (degrees, fractions)."""
    return normal_metrics(estimate, truth, torch.ones(estimate.shape[0], dtype=torch.bool))


@dataclass(frozen=True, eq=False)
class _Data:
    """Captures to fit, OLAT captures for validation, and the held-out truth of one scene."""

    captures: torch.Tensor  # (M, N, 3) fit captures
    emission: torch.Tensor  # (M, K, 3)
    exposure: float  # exposure of the fit captures
    olat_exposure: float
    olat_captures: torch.Tensor  # (K_fit, N, 3) OLAT captures of the fit lights (noise-free with noise 'off')
    test_truth: torch.Tensor  # (K_test, N, 3) noise-free e_olat * O[test]
    description: dict  # what the fit captures are, for result.json's "data"


def _prepare_data(config: InvRenderConfig, scene, rig, pixels, split) -> _Data:
    """Exposures, noisy OLAT captures, the fit captures (OLAT or simulated patterns) and test truth."""
    olat = pixels.transport.matrix.permute(1, 2, 0)  # (K, N, 3) noise-free radiance
    olat_exposure = auto_exposure(olat)
    noise_free = config.noise == "off"
    noise_model = None if noise_free else rig.noise
    bits = None if noise_free else rig.bit_depth
    generator = torch.Generator().manual_seed(config.seed)
    with torch.no_grad():
        olat_captures = sensor(olat_exposure * olat[split.fit], noise_model, bits, generator)
        test_truth = olat_exposure * olat[split.test]
        if config.patterns == "olat":
            captures = olat_captures
            emission = olat_emission(split.fit, pixels.transport.num_lights, olat_exposure)
            exposure, setting = olat_exposure, "auto"
            description = {"patterns": "olat", "M": int(split.fit.numel()), "pattern_meta": {}}
        else:
            values, pattern_meta = load_patterns(config.patterns)
            check_patterns_match_rig(values, rig.rows, rig.cols, rig.name, config.patterns)
            pattern_set = torch.as_tensor(values, dtype=torch.float32)
            setting = parse_exposure(str(config.exposure), rig)
            # simulate's auto exposure runs over the transport's pixels: the scene's masked ones.
            capture = simulate(pattern_set, pixels.transport, rig, exposure=setting, noise=noise_model, bit_depth=bits, generator=generator)
            captures, emission, exposure = capture.captures, capture.emission, capture.exposure
            description = {"patterns": str(config.patterns), "M": int(values.shape[0]), "pattern_meta": pattern_meta}
    peak = float(emission.amax())
    if not peak > 0:
        raise InputError(f"the patterns emit no light on rig {rig.name} (black patterns and no backlight): nothing to fit")
    if not EMISSION_RANGE[0] <= peak <= EMISSION_RANGE[1]:  # the fit's own check would speak of an emission the user never set
        raise InputError(f"{scene.label}: the captures need an emission peak of {peak:.3g} (exposure x display emission), outside "
                         f"[{EMISSION_RANGE[0]:g}, {EMISSION_RANGE[1]:g}] where the inverse renderer's float32 albedos stay "
                         f"representable; rescale the scene's OLAT stack (its largest value is {float(olat.amax()):.3g})"
                         + ("" if setting == "auto" else " or the exposure"))
    description.update({
        "exposure": exposure,
        "exposure_mode": "auto" if setting == "auto" else "fixed",
        "olat_exposure": olat_exposure,
        "noise": None if noise_free else {"shot": rig.noise.shot, "read_std": rig.noise.read_std, "bit_depth": rig.bit_depth},
        "saturated_fraction": float((captures >= 1.0).double().mean()),
    })
    return _Data(captures, emission, exposure, olat_exposure, olat_captures, test_truth, description)


TENSORBOARD_FOLDER = "tensorboard"
TENSORBOARD_MARKER = ".displex-invrender"
"""A file inside ``--out``'s tensorboard folder saying that invrender wrote it (so a rerun may
replace it; a tensorboard folder of other logs is refused)."""


class _TensorBoard:
    """A SummaryWriter writing into ``folder/tensorboard`` (the staged ``--out``), or nothing."""

    def __init__(self, folder: Path | None):
        self.writer = None
        if folder is None:
            return
        from torch.utils.tensorboard import SummaryWriter

        name = str(folder / TENSORBOARD_FOLDER)  # valid UTF-8: ``check_out_folder``
        (folder / TENSORBOARD_FOLDER).mkdir()
        (folder / TENSORBOARD_FOLDER / TENSORBOARD_MARKER).write_text("written by displex invrender\n")
        self.writer = SummaryWriter(log_dir=name)

    def scalars(self, prefix: str, step: int, values: dict) -> None:
        if self.writer is not None:
            for key, value in values.items():
                self.writer.add_scalar(f"{prefix}/{key}", value, step)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


def check_out_folder(out: Path) -> None:
    """Refuse, before any work, an ``--out`` whose tensorboard folder invrender did not write (a
    rerun replaces it whole), that is not a folder, or whose name is not valid UTF-8 (TensorBoard)."""
    tensorboard_folder_name(out, "--out")
    board = out / TENSORBOARD_FOLDER
    if board.exists() and not (board.is_dir() and (board / TENSORBOARD_MARKER).is_file()):
        raise InputError(f"{board} exists and was not written by displex invrender (a rerun replaces that folder); "
                         "choose another --out or move it")


def run_invrender(config: InvRenderConfig, progress: bool = True) -> dict:
    """Fit the scene, evaluate relighting on held-out lights, write the outputs; return the result.

    Args:
        config: what to run.
        progress: show tqdm bars over the model-selection fits (``basis = 'auto'``) and the final fit's steps.

    Returns:
        JSON-ready dict with ``mae`` (deg, None without ground-truth normals), ``psnr`` (dB),
        ``ssim``, ``seconds`` (wall time of data preparation, fits and evaluation), ``cpu_seconds``
        (this process's CPU time over the same span: the quiet-machine equivalent on a busy one), ``J`` and the
        details: ``specular``, ``light_model``, ``model_selection`` (curve and rule, for 'auto'),
        ``normal_error``, ``relighting``, ``basis_brdfs``, ``timings``, ``data`` and ``config``.
    """
    config.validate()
    if config.out is not None:
        check_out_folder(Path(config.out))
        if config.json is not None and Path(config.json).resolve().is_relative_to((Path(config.out) / TENSORBOARD_FOLDER).resolve()):
            raise InputError(f"--json {config.json} lies in --out's {TENSORBOARD_FOLDER} folder, which a run replaces whole; write it elsewhere")
    with torch_threads(config.threads):
        return _run(config, progress)


def _run(config: InvRenderConfig, progress: bool) -> dict:
    start, cpu_start = time.perf_counter(), time.process_time()
    timings: dict[str, float] = {}
    scene = load_scene(config.scene)
    rig = rig_for_scene(load_rig(config.rig), scene)
    pixels = scene_pixels(scene, rig)
    split = split_lights(pixels.transport.num_lights)
    data = _prepare_data(config, scene, rig, pixels, split)
    timings["data"] = time.perf_counter() - start
    grid = {"pixel_index": pixels.transport.pixel_index, "height": scene.height, "width": scene.width}
    out = None if config.out is None else Path(config.out)
    obsolete: list[Path] = []
    with contextlib.ExitStack() as stack:
        # --out's files and TensorBoard logs are staged and replace an earlier run's together at
        # the end: a failure or Ctrl-C part-way never leaves a folder mixing two runs.
        staging = None if out is None else stack.enter_context(staged_files(out, obsolete=obsolete))
        board = _TensorBoard(staging)
        try:
            output = _fit_and_evaluate(config, scene, pixels, split, data, grid, board, timings, start, cpu_start, progress, staging)
        finally:
            board.close()
        if config.json is not None:  # inside the block: an unwritable --json leaves --out as it was
            write_json(config.json, output)
        if out is not None:  # what the staged files do not replace (an earlier run's logs and selection chart) goes as they move in
            earlier_logs = [path for path in (out / TENSORBOARD_FOLDER).rglob("*") if not path.is_dir()]
            obsolete += [path for path in earlier_logs + [out / name for name in OUTPUT_FILES] if not (staging / path.relative_to(out)).exists()]
    return output


OUTPUT_FILES = ("normals.npy", "normals.png", "normals_figure.png", "weights.npy", "weights.png", "brdf_spheres.png", "relit.png",
                "model_selection.png", "config.json", "result.json")
"""Files ``--out`` receives (checked against the inputs before any work)."""


def _fit_and_evaluate(config: InvRenderConfig, scene, pixels, split, data: _Data, grid: dict, board: _TensorBoard,
                      timings: dict, start: float, cpu_start: float, progress: bool, out: Path | None) -> dict:
    """Initial estimate, light model, basis selection, final fit, evaluation and the outputs (into
    ``out``, the staged ``--out``, if given)."""
    num_lights = pixels.transport.num_lights
    pixel_index, height, width = grid["pixel_index"], grid["height"], grid["width"]
    points, lights, falloff = pixels.points.float(), pixels.lights().float(), pixels.rig.falloff
    problem = FitProblem(data.captures, data.emission, points, lights, falloff, pixel_index, height, width)

    # ---- starting point: analytic photometric stereo on the fit captures
    tick = time.perf_counter()
    initial = problem.initial_estimate()
    timings["initial_estimate"] = time.perf_counter() - tick
    if not bool(initial.valid.any()):
        # The fit would start from filled-in defaults, and the light-model test compares nothing.
        warnings.warn(f"photometric stereo flags every pixel of {scene.label} invalid under these captures (too few, identical, "
                      "dark or saturated ones; `displex evaluate` names the flags): the fit starts from default normals and its results say little",
                      DisplexWarning, stacklevel=2)

    # ---- light model: near field unless far field is indistinguishable
    tick = time.perf_counter()
    if config.geometry == "auto":
        light_model = choose_light_model(initial, data.emission, points, lights, falloff, config.selection)
        light_model["mode"] = "auto"
    else:
        light_model = {"far_field": config.geometry == "far", "mode": "forced", **light_spread(points, lights, falloff)}
    far_field = bool(light_model["far_field"])
    timings["light_model"] = time.perf_counter() - tick
    template = FitConfig(far_field=far_field, seed=config.seed, batch_pixels=config.batch_pixels, tv_weight=config.tv_weight)

    # ---- basis: a given J (specular), or model selection on validation lights
    tick = time.perf_counter()
    selection = None
    num_basis = config.num_basis()
    specular = True
    if num_basis is None:
        selection = _select(config, data, split, problem, initial, template, board, progress)
        num_basis, specular = selection.chosen.num_basis, selection.chosen.specular
    timings["model_selection"] = time.perf_counter() - tick

    # ---- final fit on all fit captures
    tick = time.perf_counter()
    fit_config = dataclasses.replace(template, num_basis=num_basis, specular=specular, iterations=config.iterations)
    with tqdm(total=config.iterations, desc="fitting", unit="step", disable=not progress) as bar:

        def log(step, values):  # called every 10 steps and at the last
            board.scalars("fit", step, values)
            bar.update(step + 1 - bar.n)

        result = problem.fit(fit_config, initial, log=log)
    timings["fit"] = time.perf_counter() - tick

    # ---- evaluation: held-out relighting and normals
    tick = time.perf_counter()
    relit = problem.relight(result, olat_emission(split.test, num_lights, data.olat_exposure))
    relighting = relighting_metrics(relit, data.test_truth, pixel_index, height, width)
    normal_error = None if pixels.normal is None else normal_error_stats(result.normal, pixels.normal)
    timings["evaluation"] = time.perf_counter() - tick
    seconds = time.perf_counter() - start
    cpu_seconds = time.process_time() - cpu_start
    board.scalars("result", 0, {"psnr": relighting["psnr"], "ssim": relighting["ssim"], **({"mae": normal_error["mae"]} if normal_error else {})})

    output = {
        "scene": scene.name,
        "mae": None if normal_error is None else normal_error["mae"],
        "psnr": relighting["psnr"],
        "ssim": relighting["ssim"],
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "J": num_basis,
        "specular": specular,
        "far_field": far_field,
        "light_model": light_model,
        "model_selection": None if selection is None else selection.describe(),
        "normal_error": normal_error,
        "relighting": relighting,
        "basis_brdfs": result.describe(),
        "pixels": int(pixel_index.numel()),
        "image": [height, width],
        "lights": {"fit": int(split.fit.numel()), "test": int(split.test.numel()), "validation": int(split.validation.numel()),
                   "test_every": TEST_EVERY, "validation_every": VALIDATION_EVERY},
        "fit": {"iterations": config.iterations, "final_rmse": result.rmse_history[-1] if result.rmse_history else None,
                "normals_searched": result.normals_searched, "seconds": result.seconds,
                "fit_config": _jsonable(asdict(fit_config))},
        "initial_estimate": {"valid_fraction": float(initial.valid.double().mean()),
                             **({"normal_error": normal_error_stats(initial.normal, pixels.normal)} if pixels.normal is not None else {})},
        "data": data.description,
        "timings": timings,
        "threads": torch.get_num_threads(),
        "config": config.to_dict(),
    }
    if out is not None:
        write_outputs(out, output, config, result, relit, data, split, pixels, selection, scene)
    return output


def _jsonable(values: dict) -> dict:
    return json.loads(json.dumps(values, default=lambda value: list(value) if isinstance(value, tuple) else str(value)))


def _select(config, data: _Data, split, problem: FitProblem, initial, template, board, progress: bool):
    """Model selection: candidates fitted on the non-validation data, scored on validation OLAT images
    (one progress-bar step per candidate fit: the sweep is most of the command's time)."""
    num_lights = problem.lights.shape[0]
    validation_position = torch.searchsorted(split.fit, split.validation)
    validation_images = data.olat_captures[validation_position]
    validation_emission = olat_emission(split.validation, num_lights, data.olat_exposure)
    candidates_problem, candidates_initial = problem, initial
    if config.patterns == "olat":
        # The fit captures are the fit lights' OLAT images: the candidates leave the validation lights' rows out.
        candidates_problem = problem.with_patterns(torch.searchsorted(split.fit, split.train))
        candidates_initial = candidates_problem.initial_estimate()

    bar = tqdm(total=config.selection.max_candidates, desc="model selection", unit="fit", disable=not progress)

    def log(num_basis, specular, candidate):
        lobes = "specular" if specular else "lambertian"
        board.scalars(f"selection/{lobes}", num_basis, {"validation_psnr": candidate.psnr})
        bar.update(1)
        bar.set_postfix(J=num_basis, lobes=lobes, psnr=f"{candidate.psnr:.2f}")

    try:
        selection = select_basis(candidates_problem, validation_emission, validation_images, template, config.selection, candidates_initial, log)
        # A sweep that stopped early (patience) is complete: end the bar full, not at e.g. 6/16.
        bar.total = bar.n
        bar.refresh()
    finally:
        bar.close()
    return selection
