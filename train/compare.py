"""Comparison of pattern design methods on held-out scenes (`displex compare`, `displex demo`).

Methods, each evaluated at every pattern count M and noise level on the test scenes with the
analytic photometric stereo (``train.evaluate.evaluate_scene``, auto exposure):
- heuristic families at their preset's default parameters (DESIGN section 6);
- learned patterns (``train.learn.train_patterns``, one run per M and seed, at the default noise);
- NLopt searches of a family's parameters (``train.search.run_search``, at the default noise);
- external pattern files (e.g. the published DDPS patterns);
- the reference: the full OLAT stack (M = K) reconstructed with Woodham least squares.
Every method is also measured at the default noise and at the same exposures on the test scenes
without their specular stacks (``specular_free_check``): the difference is what specular
reflection costs the Lambertian reconstructor.
Learning and search use the training scenes only; every number in the report comes from the
test scenes. Outputs: ``results.json`` (every number and the resolved config), ``report.md`` and
charts (``train.report``), and the learned / searched / heuristic pattern files in ``patterns/``.
A rerun with the same out folder reuses learned and searched pattern files whose config matches.
"""
from __future__ import annotations

import dataclasses
import json
import math
import multiprocessing
import multiprocessing.connection
import signal
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from capture_sim.atomic import refuse_overwriting, staged_files, write_json
from capture_sim.display import display_emission
from capture_sim.errors import DisplexWarning, InputError, check_seed
from capture_sim.rig import CONFIG_DIR, DEFAULT_RIG, Rig, load_rig, rig_file
from capture_sim.scene import scene_paths
from capture_sim.synth import GENERATOR
from capture_sim.toml_io import load_toml
from patterns.families import FAMILIES, PRESETS, get_family, make_patterns
from patterns.io import load_patterns, save_patterns
from train.capture import scene_exposure
from train.config_io import config_from_dict, config_to_dict, json_value
from train.evaluate import EvalSettings, evaluate_scene
from reconstruct.photometric_stereo import PSConfig
from train.learn import TrainConfig, auto_init_family, input_fingerprints, names_pattern_file, train_patterns
from train.search import SearchConfig, run_search, trace_chart_path
from train.scene_pixels import ScenePixels, fixed_pixel_subsets, scene_pixels
from train.scene_sets import resolve_scenes

DEFAULT_EXPOSURE_MS = 440.0
"""Exposure time per image (ms) when the rig's TOML gives no ``camera.exposure_ms``."""

MAX_NOISE_SCALE = 1e6
"""Largest noise scale compared: at 1e6 the reference rig's noise is ~5x full scale (pure noise);
far beyond, the simulated variances overflow float32 and the captures are not finite."""
SUMMARY_METRICS = ("mae", "median", "under_5", "under_10", "under_20", "under_30", "invalid_fraction", "exposure", "seconds")
"""Per-scene metrics averaged over the test scenes (each scene weighs the same)."""

_SET_BY_COMPARE = ("num_patterns", "seed", "rig", "scenes", "val_scenes", "scene_size", "scene_seed", "noise_scale", "rerender_weight")
"""TrainConfig fields that ``[learned]`` tables may not set (``rerender_weight``: learned runs are
the normal-only ones the report compares ``rerender_counts`` runs with)."""


@dataclass(frozen=True)
class SearchRun:
    """One NLopt search in a comparison (a ``[[search]]`` table; ``M`` is accepted for num_patterns)."""

    family: str
    """Family to search."""
    num_patterns: int
    """M."""
    algorithm: str = "LN_BOBYQA"
    """NLopt algorithm (``train.search.ALGORITHMS``)."""
    maxeval: int = 60
    """Largest number of objective evaluations."""
    maxtime: float | None = None
    """Wall-clock limit in seconds, or None."""
    seed: int = 0
    """NLopt, pixel-subset and noise seed."""
    pixels_per_scene: int = 3000
    """Fixed pixels per training scene in the objective (0 = all)."""

    @property
    def name(self) -> str:
        return f"search_{self.family}_M{self.num_patterns}_{self.algorithm}"


@dataclass(frozen=True)
class ExternalPatterns:
    """A pattern file to compare (an ``[[external]]`` table)."""

    name: str
    """Label in tables and charts."""
    path: str
    """Pattern file (.npz or .npy); relative paths are relative to the repository root."""


@dataclass(frozen=True)
class CompareConfig:
    """Settings of one comparison (TOML files in configs/compare/)."""

    pattern_counts: tuple[int, ...] = (2, 4, 10)
    """Numbers of patterns M to compare."""
    noise_scales: tuple[float, ...] = (0.25, 1.0, 4.0)
    """Noise levels (multipliers of the rig's noise variances) every method is evaluated at."""
    default_noise: float = 1.0
    """The noise level of the main tables, of learning and of searches; one of ``noise_scales``."""
    heuristics: tuple[str, ...] = tuple(FAMILIES)
    """Heuristic families (at their preset's default parameters); unsupported M are skipped."""
    heuristic_preset: str = "default"
    """Preset of the heuristic families: "default" (lo 0, hi 1) or "ddps" (published 0.1 / 0.9)."""
    learned: dict = field(default_factory=dict)
    """TrainConfig overrides for every learning run (steps, init, ...); the comparison sets
    num_patterns, seed, rig, scenes, val_scenes, scene_size, scene_seed and noise_scale itself."""
    learned_at: dict = field(default_factory=dict)
    """Further TrainConfig overrides per M (table keys are M), e.g. fewer steps at M = 10."""
    learned_counts: tuple[int, ...] | None = None
    """M values to learn patterns for; None = every M in ``pattern_counts``, empty = none."""
    learned_seeds: tuple[int, ...] = (0,)
    """Seeds of the learning runs at every learned M."""
    learned_seeds_at: dict = field(default_factory=dict)
    """Seeds per M replacing ``learned_seeds`` (table keys are M), to measure the seed spread."""
    search: tuple[SearchRun, ...] = ()
    """NLopt searches ([[search]] tables: family, M, algorithm, maxeval, ...)."""
    external: tuple[ExternalPatterns, ...] = ()
    """Pattern files to compare ([[external]] tables: name, path)."""
    include_olat_woodham: bool = True
    """Evaluate the reference: the full OLAT stack (M = K) with Woodham least squares."""
    specular_free_check: bool = True
    """Also evaluate every method at the default noise on the test scenes with their specular
    stacks removed (``Scene.without_specular``), at the exposures of its main evaluation, which
    separates the error of the patterns from what specular reflection costs a Lambertian
    reconstructor. Skipped, with the reason in the report, when a test scene has no usable
    separate diffuse stack."""
    rerender_counts: tuple[int, ...] = ()
    """M values with one more learning run (first seed) that adds the re-rendering loss
    (TrainConfig.rerender_weight = ``rerender_weight``), compared with the normal-only run."""
    rerender_weight: float = 1.0
    """Weight of the re-rendering loss (full-scale RMSE) against the normal loss (radians) in
    those runs."""
    solver: dict = field(default_factory=dict)
    """PSConfig overrides of the analytic photometric stereo used for every evaluation (e.g.
    ``restart_condition``, ``max_shadow_iterations``); empty = the solver's defaults."""
    eval_pixels_per_scene: int = 0
    """Masked pixels per test scene that every method is measured on: one fixed random subset per
    scene, the same for every method and noise level (0 = every masked pixel)."""
    eval_workers: int = 1
    """Processes evaluating pattern sets in parallel (each single-threaded; results do not depend
    on it). 1 evaluates in this process with torch's default threads."""
    train_scenes: tuple[str, ...] = ()
    """Scenes for learning and search; empty = the default synthetic train split."""
    test_scenes: tuple[str, ...] = ()
    """Held-out scenes of every reported number; empty = the default synthetic test split."""
    rig: str = DEFAULT_RIG
    """Rig preset or TOML path."""
    scene_size: tuple[int, int] = (128, 153)
    """Image size of the default synthetic scenes."""
    scene_seed: int = 0
    """Seed of the default synthetic scenes."""
    eval_seed: int = 0
    """Noise seed of the evaluation (``EvalSettings.seed``): every method sees the same draws."""
    out: str = "runs/compare"
    """Default output folder, relative to the repository root like the config's other paths (the
    command's --out, relative to the working directory, replaces it)."""

    def __post_init__(self):
        counts = list(self.pattern_counts) + list(self.learned_counts or ()) + list(self.rerender_counts)
        counts += [run.num_patterns for run in self.search] + list(self.learned_at) + list(self.learned_seeds_at)
        if not self.pattern_counts:
            raise InputError("pattern_counts must list at least one M")
        if any(isinstance(m, bool) or not isinstance(m, int) or m < 1 for m in counts):
            raise InputError(f"pattern counts M must be positive integers, got {counts}")
        outside = sorted({m for m in counts if m not in self.pattern_counts})
        if outside:
            raise InputError(f"M = {', '.join(map(str, outside))} (learned, re-rendering or [[search]] runs) not in pattern_counts {list(self.pattern_counts)}")
        if self.eval_pixels_per_scene < 0:
            raise InputError(f"eval_pixels_per_scene must be >= 0 (0 = every pixel), got {self.eval_pixels_per_scene}")
        if not 0 < self.rerender_weight < math.inf:
            raise InputError(f"rerender_weight must be a finite number > 0, got {self.rerender_weight!r}")
        if self.eval_workers < 1:
            raise InputError(f"eval_workers must be >= 1, got {self.eval_workers}")
        # A repeated entry would be measured and reported twice under one name (and a repeated
        # seed would fake a seed spread of 0).
        lists = {name: getattr(self, name) or () for name in ("pattern_counts", "noise_scales", "learned_seeds", "heuristics",
                                                              "learned_counts", "rerender_counts")}
        lists.update({f"learned_seeds_at.{count}": seeds for count, seeds in self.learned_seeds_at.items()})
        for name, values in lists.items():
            if len(set(values)) != len(values):
                raise InputError(f"{name} lists a value twice: {list(values)}")
        learned_counts = set(self.learned_pattern_counts()) | set(self.rerender_counts)
        unused = sorted((set(self.learned_at) | set(self.learned_seeds_at)) - learned_counts)
        if unused:
            raise InputError(f"learned_at / learned_seeds_at set M = {', '.join(map(str, unused))}, where nothing is learned "
                             f"(learned_counts {sorted(self.learned_pattern_counts())}, rerender_counts {list(self.rerender_counts)})")
        for table in (self.learned, *self.learned_at.values()):
            if names_pattern_file(table.get("init")) and not Path(table["init"]).is_file():
                raise InputError(f"learned init pattern file not found: {table['init']}")
        names = [item.name for item in self.external]
        if any(not name.strip() for name in names) or len(set(names)) != len(names):
            raise InputError(f"[[external]] names must be non-empty and distinct, got {names}")
        if not str(self.out).strip():
            raise InputError("out must be a folder path, got an empty string")
        self.ps_config()
        for item in self.external:
            if not Path(item.path).is_file():
                raise InputError(f"external pattern file {item.name!r} not found: {item.path}")
        if not self.noise_scales or not all(0 <= s <= MAX_NOISE_SCALE for s in self.noise_scales):
            raise InputError(f"noise_scales must list values in [0, {MAX_NOISE_SCALE:g}], got {list(self.noise_scales)}")
        if self.default_noise not in self.noise_scales:
            raise InputError(f"default_noise {self.default_noise} must be one of noise_scales {list(self.noise_scales)}")
        for name in self.heuristics:
            get_family(name)
        if self.heuristic_preset not in PRESETS:
            raise InputError(f"heuristic_preset must be one of {', '.join(PRESETS)}")
        forbidden = sorted(set(self.learned).union(*map(set, self.learned_at.values())) & set(_SET_BY_COMPARE))
        if forbidden:
            raise InputError(f"learned overrides may not set {', '.join(forbidden)} (the comparison sets them)")
        if not (self.heuristics or self.learned_pattern_counts() or self.search or self.external or self.rerender_counts or self.include_olat_woodham):
            raise InputError("nothing to compare: the config lists no heuristic, learned, searched or external patterns and no OLAT reference")
        if not self.learned_seeds or any(not seeds for seeds in self.learned_seeds_at.values()):
            raise InputError("learned seeds must not be empty")
        for seed in (*self.learned_seeds, *(seed for seeds in self.learned_seeds_at.values() for seed in seeds)):
            check_seed("learned seed", seed)
        check_seed("eval_seed", self.eval_seed)
        check_seed("scene_seed", self.scene_seed)
        if len({run.name for run in self.search}) != len(self.search):
            raise InputError("two [[search]] runs have the same family, M and algorithm")
        if len({item.name for item in self.external}) != len(self.external):
            raise InputError("external pattern names must be unique")
        # Every learning and search config is built now, so a bad value fails before any work.
        for count in self.learned_pattern_counts():
            self.train_config(count, self.seeds_for(count)[0])
        for count in self.rerender_counts:
            self.train_config(count, self.seeds_for(count)[0], rerender=True)
        for run in self.search:
            self.search_config(run)

    def learned_pattern_counts(self) -> tuple[int, ...]:
        """M values with learned patterns."""
        return tuple(self.pattern_counts if self.learned_counts is None else self.learned_counts)

    def seeds_for(self, num_patterns: int) -> tuple[int, ...]:
        """Learning seeds at one M."""
        return tuple(self.learned_seeds_at.get(num_patterns, self.learned_seeds))

    def train_config(self, num_patterns: int, seed: int, rerender: bool = False) -> TrainConfig:
        """The TrainConfig of the learning run at M = ``num_patterns`` with ``seed``; ``rerender``
        sets its re-rendering weight to ``rerender_weight`` (else 0: normal loss only)."""
        values = {**self.learned, **self.learned_at.get(num_patterns, {})}
        values.update(num_patterns=num_patterns, seed=seed, rig=self.rig, scenes=list(self.train_scenes),
                      val_scenes=list(self.test_scenes), scene_size=list(self.scene_size), scene_seed=self.scene_seed,
                      noise_scale=self.default_noise)
        values["rerender_weight"] = self.rerender_weight if rerender else 0.0
        return config_from_dict(TrainConfig, values, source=f"learned (M = {num_patterns})")

    def ps_config(self) -> PSConfig:
        """Solver settings of every evaluation (PSConfig defaults updated by ``solver``)."""
        return config_from_dict(PSConfig, dict(self.solver), source="solver")

    def search_config(self, run: SearchRun) -> SearchConfig:
        """The SearchConfig of one [[search]] run (training scenes, default noise)."""
        return SearchConfig(family=run.family, num_patterns=run.num_patterns, algorithm=run.algorithm, maxeval=run.maxeval,
                            maxtime=run.maxtime, seed=run.seed, scenes=tuple(self.train_scenes), noise_scale=self.default_noise,
                            rig=self.rig, scene_size=tuple(self.scene_size), scene_seed=self.scene_seed,
                            pixels_per_scene=run.pixels_per_scene)


def repository_root(config_path: Path) -> Path:
    """The folder holding the ``configs/`` folder a config file sits in (else the file's folder)."""
    config_path = Path(config_path).resolve()
    for parent in config_path.parents:
        if parent.name == "configs":
            return parent.parent
    return config_path.parent


def _resolve(path: str, root: Path) -> str:
    candidate = Path(path).expanduser()
    return str(candidate if candidate.is_absolute() else root / candidate)


def _int_keys(table, what: str) -> dict:
    if not isinstance(table, dict):
        raise InputError(f"{what} must be a table keyed by M")
    try:
        return {int(key): value for key, value in table.items()}
    except ValueError:
        raise InputError(f"{what} keys must be integers (M), got {', '.join(map(str, table))}") from None


def compare_config_from_dict(values: dict, root: Path | None = None, source: str = "compare config") -> CompareConfig:
    """Build a CompareConfig from parsed TOML; relative file paths are resolved against ``root``.

    Args:
        values: the TOML tables: top-level fields, ``[learned]``, ``[learned_at.M]``,
            ``[learned_seeds_at]``, ``[[search]]`` and ``[[external]]``.
        root: folder that relative paths (external patterns, scenes, a rig given as a .toml
            file, the output folder ``out``) are relative to; None leaves them as given (relative
            to the working directory).
        source: name of the config for error messages.
    """
    values = dict(values)
    for key in ("search", "external"):
        if not isinstance(values.get(key, []), (list, tuple)):
            raise InputError(f"{source}: {key} must be an array of tables ([[{key}]])")
    try:
        runs = []
        for table in values.get("search", ()):
            table = dict(table)
            if "M" in table:
                table["num_patterns"] = table.pop("M")
            runs.append(config_from_dict(SearchRun, table, source=f"{source} [[search]]"))
        values["search"] = tuple(runs)
        values["external"] = tuple(config_from_dict(ExternalPatterns, dict(table), source=f"{source} [[external]]")
                                   for table in values.get("external", ()))
    except (TypeError, ValueError) as err:
        if isinstance(err, InputError):
            raise
        raise InputError(f"{source}: [[search]] and [[external]] must be arrays of tables") from None
    if "learned_at" in values:
        values["learned_at"] = _int_keys(values["learned_at"], "learned_at")
        for count, table in values["learned_at"].items():
            if not isinstance(table, dict):
                raise InputError(f"{source}: learned_at.{count} must be a table of learning settings ([learned_at.{count}]), got {table!r}")
    for key in ("learned", "solver"):
        if not isinstance(values.get(key, {}), dict):
            raise InputError(f"{source}: {key} must be a table ([{key}])")
    if "learned_seeds_at" in values:
        seeds_at = _int_keys(values["learned_seeds_at"], "learned_seeds_at")
        for count, seeds in seeds_at.items():
            if not isinstance(seeds, (list, tuple)):  # the seeds themselves: CompareConfig (check_seed)
                raise InputError(f"{source}: learned_seeds_at.{count} must be a list of integer seeds, got {seeds!r}")
        values["learned_seeds_at"] = {count: tuple(seeds) for count, seeds in seeds_at.items()}
    for key in ("train_scenes", "test_scenes"):
        paths = values.get(key, [])
        if not isinstance(paths, (list, tuple)) or not all(isinstance(path, str) for path in paths):
            raise InputError(f"{source}: {key} must be a list of scene files or folders, got {paths!r}")
    if root is not None:
        values["external"] = tuple(dataclasses.replace(item, path=_resolve(item.path, root)) for item in values["external"])
        # An init pattern file, like an external one (a family name stays a name).
        def resolve_init(table: dict) -> dict:
            return {**table, "init": _resolve(table["init"], root)} if names_pattern_file(table.get("init")) else table

        if "learned" in values:
            values["learned"] = resolve_init(values["learned"])
        if "learned_at" in values:
            values["learned_at"] = {count: resolve_init(table) for count, table in values["learned_at"].items()}
        for key in ("train_scenes", "test_scenes"):
            if key in values:
                values[key] = [_resolve(path, root) for path in values[key]]
        if isinstance(values.get("rig"), str) and rig_file(values["rig"]):  # a preset name stays a name
            values["rig"] = _resolve(values["rig"], root)
        if isinstance(values.get("out"), str) and values["out"].strip():  # a blank one is refused as such
            values["out"] = _resolve(values["out"], root)
    return config_from_dict(CompareConfig, values, source=source)


def load_compare_config(path: str | Path, overrides: dict | None = None) -> CompareConfig:
    """Load ``configs/compare/NAME.toml`` (or any TOML path); non-None ``overrides`` replace fields.

    Relative paths inside the file are relative to the repository root that holds the file's
    ``configs/`` folder.
    """
    path = Path(path)
    if path.suffix != ".toml" and not path.exists():
        path = CONFIG_DIR / "compare" / f"{path}.toml"
    values = dict(load_toml(path))
    values.update({key: value for key, value in (overrides or {}).items() if value is not None})
    return compare_config_from_dict(values, repository_root(path), source=str(path))


def compare_config_to_dict(config: CompareConfig) -> dict:
    """JSON-friendly dict of a CompareConfig (the resolved config written with the results)."""
    out = config_to_dict(config)
    out["search"] = [config_to_dict(run) for run in config.search]
    out["external"] = [config_to_dict(item) for item in config.external]
    # The nested tables as well: strict JSON would write a non-finite value (angle_cap_deg = inf) as null.
    out["learned"] = {key: json_value(value) for key, value in config.learned.items()}
    out["learned_at"] = {str(m): {key: json_value(value) for key, value in v.items()} for m, v in config.learned_at.items()}
    out["learned_seeds_at"] = {str(m): list(v) for m, v in config.learned_seeds_at.items()}
    out["learned_counts"] = None if config.learned_counts is None else list(config.learned_counts)
    out["solver"] = {key: json_value(value) for key, value in config.solver.items()}
    return out


def rig_exposure_ms(rig: Rig) -> tuple[float, str]:
    """Exposure time per image (ms) from the rig's ``camera.exposure_ms``, and where it came from."""
    if rig.camera.exposure_ms is not None:
        return rig.camera.exposure_ms, f"rig {rig.name}: camera.exposure_ms"
    return DEFAULT_EXPOSURE_MS, "default (the reference camera's 440 ms; the rig gives no camera.exposure_ms)"


# ---------------------------------------------------------------------------------------------
# Pattern sets to compare
# ---------------------------------------------------------------------------------------------


@dataclass(eq=False)
class Method:
    """One pattern set in the comparison (mutable record filled during the run).

    Attributes:
        id: unique key, e.g. ``heuristic_tri_complementary_M2`` or ``learned_M4_seed1``.
        kind: "heuristic", "learned", "search", "external" or "reference".
        series: what the method is across M (a family, "learned", a search, an external name).
        label: text for tables and legends.
        num_patterns: M.
        patterns: (M, R, C, 3) set values, or "olat" for the reference.
        pattern_file: where the patterns were written or read, or None.
        cost_seconds: wall seconds spent learning or searching the patterns (None if free).
        seed: learning seed (learned methods only).
        info: extra facts for the report (e.g. a search's start and best training MAE).
        evaluations: one summary per noise level (``summarise`` plus ``noise_scale``).
        specular_free: the summary at the default noise on the specular-free test scenes, or None.
    """

    id: str
    kind: str
    series: str
    label: str
    num_patterns: int
    patterns: object
    pattern_file: str | None = None
    cost_seconds: float | None = None
    seed: int | None = None
    info: dict = field(default_factory=dict)
    evaluations: list = field(default_factory=list)
    specular_free: dict | None = None


def _reusable(path: Path, run_config, what: str) -> dict | None:
    """Meta and patterns of an existing output made with the same config (a TrainConfig or
    SearchConfig) from the same input files; None if absent. Another config, or input files that
    changed since (``train.learn.input_fingerprints``: scene, init pattern and rig files), raise."""
    if not path.exists():
        return None
    patterns, meta = load_patterns(path)
    if meta.get("config") != config_to_dict(run_config):
        raise InputError(f"{path} holds {what} made with another config; delete it or choose another output folder")
    record = _run_record(path)
    # Records of earlier versions held the scene files only: such a run cannot show it was made
    # from the current rig and init files, so it is not reused.
    if record.get("input_files") != input_fingerprints(run_config):
        raise InputError(f"{path} holds {what} made from input files (scenes, rig or init patterns) that have changed since, "
                         "or not recorded; delete it or choose another output folder")
    return {"meta": meta, "patterns": patterns}


def _run_record(path: Path) -> dict:
    record = path.with_name(path.stem + ".run.json")
    return json.loads(record.read_text()) if record.exists() else {}


def _learned_output(config: CompareConfig, num_patterns: int, seed: int, rerender: bool, pattern_dir: Path) -> tuple[str, Path, TrainConfig]:
    """Method id, pattern file and TrainConfig of one learning run."""
    method_id = f"learned{'_rerender' if rerender else ''}_M{num_patterns}_seed{seed}"
    return method_id, pattern_dir / f"{method_id}.npz", config.train_config(num_patterns, seed, rerender)


def _learning_runs(config: CompareConfig):
    """Yield (M, seed, rerender) of every learning run, normal-only ones first."""
    for count in config.learned_pattern_counts():
        for seed in config.seeds_for(count):
            yield count, seed, False
    for count in config.rerender_counts:
        yield count, config.seeds_for(count)[0], True


def _check_reusable_runs(config: CompareConfig, pattern_dir: Path) -> None:
    """Refuse (``_reusable``) before any learning starts: a folder whose learning or search outputs
    were made with another config would otherwise be refused only after minutes of the runs
    before it."""
    for count, seed, rerender in _learning_runs(config):
        _, path, train_config = _learned_output(config, count, seed, rerender, pattern_dir)
        _reusable(path, train_config, "learned patterns")
    for run in config.search:
        _reusable(pattern_dir / f"{run.name}.npz", config.search_config(run), "searched patterns")


def learned_method(config: CompareConfig, num_patterns: int, seed: int, pattern_dir: Path, progress: bool,
                   rerender: bool = False, logdir: Path | None = None) -> Method:
    """Learn (or reuse) the patterns of one learning run (``rerender``: with the re-rendering loss).

    TensorBoard logs of a new run go to ``logdir/<method id>`` when ``logdir`` is given.
    """
    method_id, path, train_config = _learned_output(config, num_patterns, seed, rerender, pattern_dir)
    existing = _reusable(path, train_config, "learned patterns")
    if existing is None:
        result = train_patterns(train_config, path, logdir=None if logdir is None else logdir / method_id, progress=progress,
                                checkpoint_mode="resume_or_fresh")
        seconds = result.seconds  # includes the sessions of a resumed run
        write_json(path.with_name(path.stem + ".run.json"), {"seconds": seconds, "steps": train_config.steps, "input_files": input_fingerprints(train_config)})
        patterns, val_history = result.patterns, result.val_history
    else:
        seconds = _run_record(path).get("seconds")
        patterns, val_history = existing["patterns"], existing["meta"].get("val_mae_history", [])
    init = auto_init_family(num_patterns) if train_config.init == "auto" else train_config.init
    info = {"steps": train_config.steps, "init": init, "rerender_weight": train_config.rerender_weight, "val_mae_history": val_history}
    if rerender:
        return Method(method_id, "rerender", "learned_rerender", f"learned, normal + re-rendering loss (weight {train_config.rerender_weight:g})",
                      num_patterns, patterns, str(path), seconds, seed, info)
    return Method(method_id, "learned", "learned", f"learned (seed {seed})", num_patterns, patterns, str(path), seconds, seed, info)


def searched_method(config: CompareConfig, run: SearchRun, pattern_dir: Path, progress: bool, logdir: Path | None = None) -> Method:
    """Run (or reuse) one NLopt search (TensorBoard logs of a new run under ``logdir/<run name>``)."""
    search_config = config.search_config(run)
    path = pattern_dir / f"{run.name}.npz"
    existing = _reusable(path, search_config, "searched patterns")
    if existing is None:
        meta = run_search(search_config, path, logdir=None if logdir is None else logdir / run.name, progress=progress)
        patterns = load_patterns(path)[0]
        write_json(path.with_name(path.stem + ".run.json"), {"seconds": meta["seconds"], "input_files": input_fingerprints(search_config)})
    else:
        meta, patterns = existing["meta"], existing["patterns"]
    info = {key: meta[key] for key in ("start_mae", "best_mae", "evaluations", "stop_reason", "sharpness")}
    info["trace_png"] = str(trace_chart_path(path))
    return Method(run.name, "search", f"search:{run.family}:{run.algorithm}", f"{run.family} + {run.algorithm}", run.num_patterns,
                  patterns, str(path), meta["seconds"], info=info)


def external_methods(config: CompareConfig, rig) -> tuple[list[Method], list[dict]]:
    """The ``[[external]]`` pattern sets that fit the rig and the compared M, and the others with
    the reason they are skipped.

    Raises:
        InputError: a file is unreadable or its values are not patterns (``load_patterns``).
    """
    methods: list[Method] = []
    skipped: list[dict] = []
    for item in config.external:
        patterns, _ = load_patterns(item.path)
        count = patterns.shape[0]
        if patterns.shape[1:3] != (rig.rows, rig.cols):
            reason = f"patterns are {patterns.shape[1]} x {patterns.shape[2]}, the rig is {rig.rows} x {rig.cols}"
            skipped.append({"method": item.name, "M": count, "reason": reason})
            # Skipped, not refused: one config serves rigs of several grids, but a file listed for
            # this one and left out should not go unnoticed until the report is read.
            warnings.warn(f"external pattern file {item.path} skipped: {reason}", DisplexWarning, stacklevel=2)
        elif count not in config.pattern_counts:
            skipped.append({"method": item.name, "M": count, "reason": "M is not in pattern_counts"})
            warnings.warn(f"external pattern file {item.path} skipped: its M = {count} is not in pattern_counts "
                          f"{list(config.pattern_counts)}", DisplexWarning, stacklevel=2)
        else:
            methods.append(Method(f"external_{item.name}", "external", f"external:{item.name}", item.name, count, patterns, item.path))
    return methods, skipped


def collect_methods(config: CompareConfig, rig, pattern_dir: Path, progress: bool, logdir: Path | None = None) -> tuple[list[Method], list[dict], dict]:
    """Every pattern set of the comparison, the skipped ones with the reason, and phase timings.

    Learning and searches run here (TensorBoard logs under ``logdir`` when given).
    """
    # External files are read first: an unreadable one stops the comparison before minutes of learning.
    external, skipped = external_methods(config, rig)
    _check_reusable_runs(config, pattern_dir)
    methods: list[Method] = []
    timings = {"learning_seconds": 0.0, "search_seconds": 0.0}
    for count in config.pattern_counts:
        for name in config.heuristics:
            family = get_family(name)
            if not family.supports(count, rig.rows, rig.cols):
                skipped.append({"method": name, "M": count, "reason": f"{name} supports M = {family.min_patterns}..{family.max_patterns(rig.rows, rig.cols)}"})
                continue
            try:
                patterns = make_patterns(name, count, rig.rows, rig.cols, preset=config.heuristic_preset).numpy()
            except InputError as error:  # identical patterns on a small grid: a skip, like an unsupported M
                skipped.append({"method": name, "M": count, "reason": str(error)})
                continue
            # The file is written with the results (``run_compare``): an interrupted rerun with
            # another preset would otherwise leave the last results pointing at rewritten files.
            path = pattern_dir / f"heuristic_{name}_M{count}.npz"
            methods.append(Method(f"heuristic_{name}_M{count}", "heuristic", name, name, count, patterns, str(path)))
    for count, seed, rerender in _learning_runs(config):
        start = time.perf_counter()
        methods.append(learned_method(config, count, seed, pattern_dir, progress, rerender=rerender, logdir=logdir))
        timings["learning_seconds"] += time.perf_counter() - start
    for run in config.search:  # CompareConfig refuses runs whose M is not in pattern_counts
        start = time.perf_counter()
        methods.append(searched_method(config, run, pattern_dir, progress, logdir))
        timings["search_seconds"] += time.perf_counter() - start
    methods += external
    if config.include_olat_woodham:
        methods.append(Method("olat_woodham", "reference", "olat_woodham", f"OLAT + Woodham (M = {rig.num_lights})", rig.num_lights, "olat"))
    return methods, skipped, timings


# ---------------------------------------------------------------------------------------------
# Evaluation
# ---------------------------------------------------------------------------------------------


def summarise(scene_metrics: list[dict], num_patterns: int, exposure_ms: float, white_exposures: list[float]) -> dict:
    """Scene-averaged metrics of one method at one noise level, with capture and compute time.

    Capture time follows DESIGN section 5, M x exposure time per image, with the exposure time
    scaled by the exposure gain e the method needed: the sensor's noise is added after e in
    full-scale units (section 3), so e acts as integration time, and a dim pattern set that auto
    exposure lifts with a large e takes that much longer at the rig. The rig's exposure time is
    taken as that of the all-white display, whose gain on the scene is ``white_exposures``:
    t = exposure_ms x e / e_white per image.

    Args:
        scene_metrics: ``evaluate_scene`` metrics per test scene (with its ``exposure`` e).
        num_patterns: M (images captured).
        exposure_ms: exposure time per image of the all-white display, milliseconds.
        white_exposures: e_white per test scene (``white_exposures``), in ``scene_metrics`` order.

    Returns:
        dict: every ``SUMMARY_METRICS`` entry averaged over scenes (``seconds`` renamed
        ``compute_seconds``: simulation plus reconstruction wall time per scene),
        ``capture_seconds`` (the scene mean of M x exposure_ms x e / e_white, in seconds), and the
        per-scene values under ``scenes``.
    """
    summary = {key: float(np.mean([metrics[key] for metrics in scene_metrics])) for key in SUMMARY_METRICS}
    summary["compute_seconds"] = summary.pop("seconds")
    captures = [num_patterns * exposure_ms / 1000.0 * metrics["exposure"] / white for metrics, white in zip(scene_metrics, white_exposures, strict=True)]
    summary["capture_seconds"] = float(np.mean(captures))
    summary["scenes"] = [{**{key: metrics[key] for key in ("name", "mae", "median", "invalid_fraction", "exposure", "seconds")}, "capture_seconds": capture}
                         for metrics, capture in zip(scene_metrics, captures)]
    return summary


def white_exposures(scenes: list[ScenePixels], rig) -> dict[str, list[float]]:
    """Auto exposure gain e_white of each scene under the all-white display (every superpixel at
    set value 1, the brightest pattern), over all its masked pixels: the reference of capture
    times (``summarise``), in the units of the two kinds of gain.

    Returns:
        {"patterns": e_white per scene, "olat": the same in the units of the OLAT reference's gain},
        which multiplies the raw OLAT stack (radiance per unit display intensity) where a pattern's
        multiplies the display's emission s (P + B)^gamma: a superpixel lit at set value 1 emits
        s (1 + B_k)^gamma, so the reference's e_white is e_white s mean_k (1 + B_k)^gamma.
    """
    white = torch.ones((1, rig.rows, rig.cols, 3))
    whites = [scene_exposure(pixels, white) for pixels in scenes]
    lit = float(display_emission(white, rig.backlight_flat(), rig.gamma, rig.scale).mean())
    return {"patterns": whites, "olat": [value * lit for value in whites]}


def _whites_of(method: "Method", whites: dict[str, list[float]]) -> list[float]:
    return whites["olat" if method.kind == "reference" else "patterns"]


def evaluation_columns(scenes, pixels_per_scene: int, seed: int) -> list:
    """Per scene: sorted (P,) indices of a fixed random subset of ``pixels_per_scene`` masked
    pixels (seeded by ``seed`` and the scene index), or None to measure every masked pixel."""
    return fixed_pixel_subsets(scenes, pixels_per_scene, seed, offset=500)


SAME_PATTERNS_TOLERANCE = 1e-6
"""Pattern sets whose values differ by at most this are the same set: a family made here and the
published file of it differ by float rounding (up to ~1e-7), far below one display level."""


def _same_patterns(first, second) -> bool:
    if isinstance(first, str) or isinstance(second, str):  # 'olat': the full OLAT stack
        return isinstance(first, str) and isinstance(second, str) and first == second
    first, second = np.asarray(first, dtype=np.float32), np.asarray(second, dtype=np.float32)
    return first.shape == second.shape and float(np.abs(first - second).max(initial=0.0)) <= SAME_PATTERNS_TOLERANCE


def first_with_same_patterns(methods: list) -> list[int]:
    """For each method, the index of the first method whose patterns are the same (itself if none)."""
    firsts: list[int] = []
    representative = []
    for index, method in enumerate(methods):
        match = next((first for first in firsts if _same_patterns(methods[first].patterns, method.patterns)), None)
        if match is None:
            firsts.append(index)
            match = index
        representative.append(match)
    return representative


_WORKER_STATE: dict = {}
"""Scenes, pixel subsets and solver settings of the evaluation workers (inherited by fork)."""


def _init_worker() -> None:
    # Forked children must not enter the parent's OpenMP pool (as torch's DataLoader workers).
    torch.set_num_threads(1)
    # Ctrl-C reaches the whole process group: the parent stops the workers (``_evaluate_in_workers``).
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _evaluate_keyed(job: tuple) -> tuple:
    """``_evaluate_job`` of ``job`` = (key, patterns, reference, noise, exposures), returned with its key."""
    key, *arguments = job
    return key, _evaluate_job(*arguments)


def _worker_main(jobs: list, connection) -> None:
    """A forked evaluation worker: runs its share of the jobs and sends ("result", (key, metrics))
    per job, or ("error", exception) and stops."""
    _init_worker()
    try:
        for job in jobs:
            connection.send(("result", _evaluate_keyed(job)))
    except Exception as error:  # the parent re-raises it (an InputError stays one clear line)
        try:
            connection.send(("error", error))
        except Exception:  # an exception that cannot be pickled
            connection.send(("error", RuntimeError(f"{type(error).__name__}: {error}")))
    finally:
        connection.close()


def _evaluate_in_workers(jobs: list, workers: int, on_result: Callable[[tuple, list], None], poll_seconds: float = 0.2) -> None:
    """Run ``_evaluate_keyed`` over ``jobs`` in ``workers`` forked processes (job i in worker
    i mod workers; they inherit the scenes), calling ``on_result(key, metrics)`` as results arrive.

    Each worker reports on its own pipe and shares no lock with the parent, so the parent can stop
    them at any moment: on an error or Ctrl-C it kills them and re-raises. (A multiprocessing Pool
    can hang there: its terminate waits for a queue lock that an idle or dying worker holds.)
    The parent waits in slices of ``poll_seconds`` so that a Ctrl-C that the kernel hands to
    another thread is acted on promptly.
    """
    context = multiprocessing.get_context("fork")
    processes, pending = [], {}
    try:
        for index in range(workers):
            share = jobs[index::workers]
            if not share:
                continue
            receiver, sender = context.Pipe(duplex=False)
            process = context.Process(target=_worker_main, args=(share, sender), daemon=True)
            processes.append(process)  # before start: a Ctrl-C during the start must still stop it
            pending[receiver] = len(share)
            process.start()
            sender.close()  # the parent keeps the receiving end only, so a dead worker reads as EOF
        while pending:
            for connection in multiprocessing.connection.wait(list(pending), timeout=poll_seconds):
                try:
                    kind, payload = connection.recv()
                except EOFError:
                    raise RuntimeError("an evaluation worker exited before finishing its jobs (out of memory?)") from None
                if kind == "error":
                    raise payload
                on_result(*payload)
                pending[connection] -= 1
                if not pending[connection]:
                    del pending[connection]
    finally:
        for process in processes:
            if process.pid is not None:  # started
                process.kill()  # a no-op on a finished one
                process.join()
        for connection in pending:
            connection.close()


def _evaluate_job(patterns, reference: bool, noise: float, exposures=None) -> list[dict]:
    """Per-scene metrics of one pattern set at one noise level (runs in a worker or in-process);
    ``exposures`` (one gain per scene) replaces auto exposure."""
    state = _WORKER_STATE
    settings = EvalSettings(method="woodham" if reference else "ps", noise_scale=noise, seed=state["seed"], ps=state["ps"])
    if not isinstance(patterns, str):
        patterns = torch.as_tensor(np.asarray(patterns, dtype=np.float32))
    scenes = list(zip(state["scenes"], state["columns"]))
    per_scene = [settings] * len(scenes) if exposures is None else [dataclasses.replace(settings, exposure=float(gain)) for gain in exposures]
    return [evaluate_scene(pixels, patterns, scene_settings, index, subset).metrics
            for index, ((pixels, subset), scene_settings) in enumerate(zip(scenes, per_scene))]


def measure_methods(methods: list[Method], scenes, config: CompareConfig, noise_scales, progress: bool, what: str = "evaluating",
                    exposures: dict | None = None) -> tuple[list[int], dict]:
    """Per-scene metrics of every distinct pattern set at every noise level on ``scenes``.

    Every method is measured on the same pixels (``config.eval_pixels_per_scene``) with the same
    noise draws, and a pattern set that occurs twice (e.g. an external file equal to a heuristic
    family) is measured once. With ``config.eval_workers`` > 1 the (pattern set, noise level) jobs
    run in forked processes.

    Args:
        methods: the pattern sets.
        scenes: prepared test scenes (``ScenePixels``), measured in this order.
        config: pixel subsets, solver, noise seed and workers.
        noise_scales: noise levels (multipliers of the rig's noise variances).
        progress: show a progress bar labelled ``what``.
        exposures: optional {index of a method: [exposure gain per scene]} fixing the exposure of
            that method's jobs (auto exposure otherwise).

    Returns:
        ``first_with_same_patterns(methods)`` and {(index of that first method, noise): [metrics
        per scene]}.
    """
    _WORKER_STATE.update(scenes=scenes, columns=evaluation_columns(scenes, config.eval_pixels_per_scene, config.eval_seed),
                         ps=config.ps_config(), seed=config.eval_seed)
    representative = first_with_same_patterns(methods)
    exposures = exposures or {}
    jobs = [(key, methods[key], float(noise)) for key in sorted(set(representative)) for noise in noise_scales]
    metrics: dict = {}
    bar = tqdm(total=len(jobs), desc=what, unit="set", disable=not progress)
    try:
        if config.eval_workers > 1 and len(jobs) > 1:
            def collect(key, result):
                metrics[key] = result
                bar.update(1)

            keyed = [((key, noise), method.patterns, method.kind == "reference", noise, exposures.get(key)) for key, method, noise in jobs]
            _evaluate_in_workers(keyed, config.eval_workers, collect)
        else:
            for key, method, noise in jobs:
                metrics[(key, noise)] = _evaluate_job(method.patterns, method.kind == "reference", noise, exposures.get(key))
                bar.update(1)
    finally:
        bar.close()
        _WORKER_STATE.clear()
    return representative, metrics


def evaluate_methods(methods: list[Method], scenes, config: CompareConfig, exposure_ms: float, whites: dict, progress: bool) -> None:
    """Fill every method's ``evaluations`` with one summary per noise level (test scenes prepared
    once by the caller; see ``measure_methods``; ``exposure_ms`` as ``summarise``, ``whites`` from
    ``white_exposures``)."""
    representative, metrics = measure_methods(methods, scenes, config, config.noise_scales, progress)
    for method, key in zip(methods, representative):
        if methods[key] is not method:
            method.info["same_patterns_as"] = methods[key].id
        method.evaluations = [{"noise_scale": float(noise), **summarise(metrics[(key, float(noise))], method.num_patterns, exposure_ms, _whites_of(method, whites))}
                              for noise in config.noise_scales]


def specular_free_scenes(scenes: list, rig) -> tuple[list | None, str | None]:
    """The test scenes (``Scene``, as loaded) without their specular stacks, prepared
    (``ScenePixels``), or (None, the reason) when one of them cannot be made so
    (``Scene.without_specular``)."""
    try:
        return [scene_pixels(scene.without_specular(), rig, require_normals=True) for scene in scenes], None
    except InputError as error:
        return None, str(error)


def evaluate_specular_free(methods: list[Method], scenes, config: CompareConfig, exposure_ms: float, whites: dict, progress: bool) -> None:
    """Fill every method's ``specular_free`` summary: the default noise on the specular-free
    ``scenes`` at the exposure each scene had in the method's main evaluation (``evaluate_methods``
    ran first), so that only the specular light differs, not the exposure it forced."""
    default = float(config.default_noise)
    exposures = {index: [scene["exposure"] for scene in next(e for e in method.evaluations if math.isclose(e["noise_scale"], default))["scenes"]]
                 for index, method in enumerate(methods)}
    representative, metrics = measure_methods(methods, scenes, config, (default,), progress, "specular-free check", exposures)
    for method, key in zip(methods, representative):
        method.specular_free = summarise(metrics[(key, default)], method.num_patterns, exposure_ms, _whites_of(method, whites))


def method_record(method: Method, out_dir: Path) -> dict:
    """JSON record of one evaluated method (pattern file path relative to ``out_dir`` when inside it)."""
    pattern_file = method.pattern_file
    if pattern_file is not None:
        try:
            pattern_file = str(Path(pattern_file).resolve().relative_to(out_dir.resolve()))
        except ValueError:
            pass
    info = dict(method.info)
    return {"id": method.id, "kind": method.kind, "series": method.series, "label": method.label, "M": method.num_patterns,
            "seed": method.seed, "pattern_file": pattern_file, "cost_seconds": method.cost_seconds, "info": info,
            "evaluations": method.evaluations, "specular_free": method.specular_free}


def run_compare(config: CompareConfig, out_dir: Path, progress: bool = True) -> dict:
    """Learn, search and evaluate every method; write results.json, report.md and charts.

    Args:
        config: the comparison.
        out_dir: output folder (patterns/, results.json, report.md, *.png).
        progress: show progress bars.

    Returns:
        The results dict written to ``results.json``: resolved ``config``, ``rig``, ``exposure_ms``,
        ``white_exposures`` (e_white per test scene, ``white_exposures``), scene names, ``methods`` (each with ``evaluations`` per noise level), ``skipped``,
        ``summary`` (learned vs best heuristic, seed spread) and ``timings``.
    """
    from train.report import CHARTS, summary_tables, write_report

    out_dir = Path(out_dir)
    began = time.perf_counter()
    # A file where the folder goes, or a folder nothing can be written into: refused now, not
    # when the results are written after the work.
    refuse_overwriting([("results", out_dir / "results.json")], [])
    pattern_dir = out_dir / "patterns"
    if (pattern_dir / "__init__.py").exists():  # e.g. out = "." in the repository root
        raise InputError(f"compare output folder {out_dir} holds a Python package patterns/ (the source tree?), "
                         "into which compare would write its pattern files; choose another folder")
    for item in config.external:
        if Path(item.path).resolve().is_relative_to(pattern_dir.resolve()):
            raise InputError(f"[[external]] {item.name}: {item.path} lies in {pattern_dir}, whose files compare rewrites; "
                             "copy it elsewhere or choose another output folder")
    _check_scene_lists(config)
    rig = load_rig(config.rig)
    exposure_ms, exposure_source = rig_exposure_ms(rig)
    resolved = compare_config_to_dict(config)
    test_raw = resolve_scenes(tuple(config.test_scenes), "test", rig, tuple(config.scene_size), config.scene_seed)
    test_scenes = [scene_pixels(scene, rig, require_normals=True) for scene in test_raw]
    free_scenes, free_reason = specular_free_scenes(test_raw, rig) if config.specular_free_check else (None, None)
    del test_raw  # learning runs next: keep the prepared pixels only, not the full-frame stacks
    methods, skipped, timings = collect_methods(config, rig, pattern_dir, progress, logdir=out_dir / "tensorboard")
    if not methods:
        # CompareConfig refuses configs that list nothing, so every listed method was skipped.
        reasons = "; ".join(f"{entry['method']} at M = {entry['M']}: {entry['reason']}" for entry in skipped)
        raise InputError(f"nothing to compare ({reasons})")
    start = time.perf_counter()
    whites = white_exposures(test_scenes, rig)
    evaluate_methods(methods, test_scenes, config, exposure_ms, whites, progress)
    timings["evaluation_seconds"] = time.perf_counter() - start
    specular_free = {"enabled": config.specular_free_check}
    if free_reason is not None:
        specular_free["skipped"] = free_reason
    elif free_scenes is not None:
        start = time.perf_counter()
        evaluate_specular_free(methods, free_scenes, config, exposure_ms, whites, progress)
        timings["specular_free_seconds"] = time.perf_counter() - start
    results = {
        "config": resolved,
        "rig": rig.name,
        "grid": [rig.rows, rig.cols],
        "exposure_ms": exposure_ms,
        "exposure_ms_source": exposure_source,
        "white_exposures": whites["patterns"],  # e_white per test scene, in the order of test_scenes
        "default_noise": config.default_noise,
        "noise_scales": [float(s) for s in config.noise_scales],
        "pattern_counts": list(config.pattern_counts),
        "test_scenes": [pixels.name for pixels in test_scenes],
        "test_pixels": sum(pixels.num_pixels for pixels in test_scenes),
        "methods": [method_record(method, out_dir) for method in methods],
        "specular_free": specular_free,
        "skipped": skipped,
        "timings": timings,
    }
    results["summary"] = summary_tables(results)
    results["timings"]["total_seconds"] = time.perf_counter() - began
    results["report"] = str(out_dir / "report.md")
    # The heuristic pattern files, report, charts, results and config are moved into place
    # together: a run refused or interrupted part-way leaves them all describing the last
    # finished run (learned and searched files are kept per settings, see ``_reusable``).
    obsolete: list = []  # an earlier run's charts that this report does not show: they would contradict it
    with staged_files(out_dir, last=("results.json", "config.json"), obsolete=obsolete) as staging:
        for method in methods:
            if method.kind == "heuristic":
                save_patterns(staging / "patterns" / Path(method.pattern_file).name, method.patterns,
                              {"family": method.series, "preset": config.heuristic_preset, "made_by": "displex compare", "rig": rig.name})
        write_report(results, out_dir, {method.id: method.patterns for method in methods if not isinstance(method.patterns, str)}, staging)
        obsolete += [out_dir / name for name in CHARTS.values() if not (staging / name).exists()]
        write_json(staging / "results.json", results)
        write_json(staging / "config.json", resolved)
    return results


def _check_scene_lists(config: CompareConfig) -> None:
    """Refuse a test scene file listed twice (it would weigh twice in every mean); warn when a
    test scene is also a training scene of the learning or search runs (its MAE is not held out)."""
    test_files = [path.resolve() for path in scene_paths(config.test_scenes)]
    repeated = sorted({str(path) for path in test_files if test_files.count(path) > 1})
    if repeated:
        raise InputError(f"test_scenes name the same scene file twice: {', '.join(repeated)}")
    if config.learned_pattern_counts() or config.rerender_counts or config.search:
        shared = sorted(set(test_files) & {path.resolve() for path in scene_paths(config.train_scenes)})
        if shared:
            warnings.warn(f"{len(shared)} test scene(s) are also training scenes ({', '.join(path.name for path in shared)}): "
                          "their MAE is not measured on held-out scenes", DisplexWarning, stacklevel=2)


def _scene_set_matches(index_path: Path, rig, config: CompareConfig) -> bool:
    """Whether a synthesised scene set (its ``index.json``) is the one ``run_demo`` would write:
    this generator, rig, size and seed, without cast shadows. A rerun then reuses it instead of
    silently using scenes of other settings (e.g. a ``scenes synth --cast-shadows`` set)."""
    if not index_path.exists():
        return False
    try:
        index = json.loads(index_path.read_text())
    except (OSError, ValueError):
        return False
    wanted = {"generator": GENERATOR, "rig": rig.name, "height": config.scene_size[0], "width": config.scene_size[1],
              "seed": config.scene_seed, "cast_shadows": False}
    if not (isinstance(index, dict) and all(index.get(key) == value for key, value in wanted.items())):
        return False
    # Every listed scene file is still there, and no other scene file has been added beside them.
    splits = index.get("splits")
    if not isinstance(splits, dict) or set(splits) != {"train", "test"}:
        return False
    folder = index_path.parent
    try:
        listed = {(folder / entry["file"]).resolve() for split in splits.values() for entry in split}
    except (TypeError, KeyError):
        return False
    present = {path.resolve() for split in splits for path in (folder / split).glob("*.npz")}
    return listed == present


def run_demo(out_dir: Path, progress: bool = True, config_path: Path | None = None, steps: int | None = None) -> dict:
    """The demo: synthesise the default scenes into ``out_dir/scenes`` and run the demo comparison.

    Args:
        out_dir: output folder: ``scenes/`` (train and test splits) and the comparison outputs.
        progress: show progress bars.
        config_path: comparison config (default ``configs/compare/demo.toml``).
        steps: learning steps of every learned pattern set (None: the config's, per M).

    Returns:
        The comparison results (see ``run_compare``); prints where the report is.
    """
    from capture_sim.synth import write_scene_set

    out_dir = Path(out_dir)
    config = load_compare_config(config_path or CONFIG_DIR / "compare" / "demo.toml")
    if steps is not None:
        per_m = {count: {k: v for k, v in values.items() if k != "steps"} for count, values in config.learned_at.items()}
        config = dataclasses.replace(config, learned={**config.learned, "steps": steps}, learned_at=per_m)
    rig = load_rig(config.rig)
    scene_dir = out_dir / "scenes"
    if not _scene_set_matches(scene_dir / "index.json", rig, config):
        write_scene_set(scene_dir, rig, config.scene_size[0], config.scene_size[1], config.scene_seed, progress=progress)
    # Absolute paths: the learned and searched runs record them in their configs, and a rerun
    # reuses those runs however --out is spelled and whatever the working directory.
    scene_dir = scene_dir.resolve()
    config = dataclasses.replace(config, train_scenes=(str(scene_dir / "train"),), test_scenes=(str(scene_dir / "test"),))
    results = run_compare(config, out_dir, progress)
    print(f"demo finished in {results['timings']['total_seconds']:.0f} s; report: {results['report']}")
    return results
