"""Settings of a comparison (`displex compare --config`): the frozen ``CompareConfig`` with its
learning runs, searches and external pattern files, read from TOML with paths relative to the
folder that holds ``configs/``, and the exposure time per image that capture times use."""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path


from capture_sim.errors import InputError, check_seed
from capture_sim.rig import CONFIG_DIR, DEFAULT_RIG, Rig, check_noise_scale
from capture_sim.toml_io import load_toml
from patterns.families import FAMILIES, PRESETS, get_family
from patterns.io import names_pattern_file
from reconstruct.photometric_stereo import PSConfig
from train.config_io import config_from_dict, config_to_dict, json_value, repository_root, resolve_file_fields, resolve_path
from train.learn import TrainConfig
from train.scene_sets import configured_scene_size
from train.search import SearchConfig


DEFAULT_EXPOSURE_MS = 440.0
"""Exposure time per image (ms) when the rig's TOML gives no ``camera.exposure_ms``."""

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
    """NLopt, pixel-subset and noise seed, and that of a random family's start values."""
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
    """Pattern file (.npz or .npy); a relative path is relative to the folder holding the config's
    ``configs/`` folder (``train.config_io.repository_root``), like the config's other paths."""


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
    num_patterns, seed, rig, scenes, val_scenes, scene_size, scene_seed, noise_scale and
    rerender_weight itself (``rerender_weight`` / ``rerender_counts`` above set the latter)."""
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
    """Processes evaluating pattern sets in parallel, each single-threaded; 1 evaluates in this
    process on torch's threads (``displex --threads``). Sums split across threads round
    differently, so numbers evaluated in this process can differ in their last digits (a few
    hundredths of a degree in a scene's MAE) with the thread count, which ``results.json`` records
    (``threads``); with ``--threads 1`` nothing depends on it."""
    train_scenes: tuple[str, ...] = ()
    """Scenes for learning and search; empty = the default synthetic train split."""
    test_scenes: tuple[str, ...] = ()
    """Held-out scenes of every reported number; empty = the default synthetic test split."""
    rig: str = DEFAULT_RIG
    """Rig preset or TOML path."""
    scene_size: tuple[int, int] | None = None
    """Image size (height, width) of the default synthetic scenes; None (unset) is replaced on
    construction by a quarter of the rig camera's resolution (``capture_sim.synth.default_scene_size``:
    128 x 153 on the reference rig)."""
    scene_seed: int = 0
    """Seed of the default synthetic scenes."""
    eval_seed: int = 0
    """Noise seed of the evaluation (``EvalSettings.seed``): every method sees the same draws."""
    out: str = "runs/compare"
    """Default output folder, relative like the config's other paths (to the folder holding its
    ``configs/`` folder, or its own folder outside one); the command's --out, relative to the
    working directory, replaces it."""

    def __post_init__(self):
        object.__setattr__(self, "scene_size", configured_scene_size(self.scene_size, self.rig))
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
        alone = sorted(set(self.rerender_counts) - set(self.learned_pattern_counts()))
        if alone:  # the report compares each with the normal-only run of its M and first seed
            raise InputError(f"rerender_counts M = {', '.join(map(str, alone))} have no normal-only learning run to compare with "
                             f"(learned_counts {sorted(self.learned_pattern_counts())}): add them there")
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
        if not self.noise_scales:
            raise InputError("noise_scales must list at least one noise scale")
        for scale in self.noise_scales:
            check_noise_scale("noise_scales value", scale)
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
        clashing = sorted({item.name for item in self.external} & set(self.heuristics))
        if clashing:  # the report's rows and legends would carry one label twice
            raise InputError(f"external pattern names {', '.join(clashing)} are also heuristic families of this comparison; rename them")
        # Every learning and search config is built now, so a bad value fails before any work; a
        # misspelt [learned] key fails even where nothing is learned (its values are checked merged
        # with each M's table, where they are used).
        unknown = sorted(set(self.learned) - {item.name for item in dataclasses.fields(TrainConfig)})
        if unknown:
            raise InputError(f"learned: unknown key(s) {', '.join(unknown)}")
        # [learned] alone too: a value that every [learned_at.M] table overrides is still wrong, and
        # one of a config that learns nothing (checked at the first compared M) as well.
        count = (self.learned_pattern_counts() or self.rerender_counts or self.pattern_counts)[0]
        self._train_config(self.learned, count, self.seeds_for(count)[0], False, source="learned")
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
        return self._train_config(values, num_patterns, seed, rerender, source=f"learned (M = {num_patterns})")

    def _train_config(self, values: dict, num_patterns: int, seed: int, rerender: bool, source: str) -> TrainConfig:
        """TrainConfig from the override ``values`` plus the fields the comparison sets."""
        values = dict(values)
        values.update(num_patterns=num_patterns, seed=seed, rig=self.rig, scenes=list(self.train_scenes),
                      val_scenes=list(self.test_scenes), scene_size=list(self.scene_size), scene_seed=self.scene_seed,
                      noise_scale=self.default_noise)
        values["rerender_weight"] = self.rerender_weight if rerender else 0.0
        return config_from_dict(TrainConfig, values, source=source)

    def ps_config(self) -> PSConfig:
        """Solver settings of every evaluation (PSConfig defaults updated by ``solver``)."""
        return config_from_dict(PSConfig, dict(self.solver), source="solver")

    def search_config(self, run: SearchRun) -> SearchConfig:
        """The SearchConfig of one [[search]] run (training scenes, default noise)."""
        return SearchConfig(family=run.family, num_patterns=run.num_patterns, algorithm=run.algorithm, maxeval=run.maxeval,
                            maxtime=run.maxtime, seed=run.seed, scenes=tuple(self.train_scenes), noise_scale=self.default_noise,
                            rig=self.rig, scene_size=tuple(self.scene_size), scene_seed=self.scene_seed,
                            pixels_per_scene=run.pixels_per_scene)


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
            if "M" in table and "num_patterns" in table:
                raise InputError(f"{source} [[search]]: M and num_patterns are the same setting; give one")
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
        values["learned_at"] = _int_keys(values["learned_at"], f"{source}: learned_at")
        for count, table in values["learned_at"].items():
            if not isinstance(table, dict):
                raise InputError(f"{source}: learned_at.{count} must be a table of learning settings ([learned_at.{count}]), got {table!r}")
    for key in ("learned", "solver"):
        if not isinstance(values.get(key, {}), dict):
            raise InputError(f"{source}: {key} must be a table ([{key}])")
    if "learned_seeds_at" in values:
        seeds_at = _int_keys(values["learned_seeds_at"], f"{source}: learned_seeds_at")
        for count, seeds in seeds_at.items():
            if not isinstance(seeds, (list, tuple)):  # the seeds themselves: CompareConfig (check_seed)
                raise InputError(f"{source}: learned_seeds_at.{count} must be a list of integer seeds, got {seeds!r}")
        values["learned_seeds_at"] = {count: tuple(seeds) for count, seeds in seeds_at.items()}
    for key in ("train_scenes", "test_scenes"):
        paths = values.get(key, [])
        if not isinstance(paths, (list, tuple)) or not all(isinstance(path, str) for path in paths):
            raise InputError(f"{source}: {key} must be a list of scene files or folders, got {paths!r}")
    if root is not None:
        values["external"] = tuple(dataclasses.replace(item, path=resolve_path(item.path, root)) for item in values["external"])
        values = resolve_file_fields(values, root)
        if "learned" in values:  # an init pattern file, like an external one
            values["learned"] = resolve_file_fields(values["learned"], root)
        if "learned_at" in values:
            values["learned_at"] = {count: resolve_file_fields(table, root) for count, table in values["learned_at"].items()}
    return config_from_dict(CompareConfig, values, source=source)


def load_compare_config(path: str | Path, overrides: dict | None = None) -> CompareConfig:
    """Load ``configs/compare/NAME.toml`` (or any TOML path); non-None ``overrides`` replace fields.

    Relative paths inside the file are relative to the folder that holds the file's ``configs/``
    folder, or to the file's own folder when it is not inside one (``train.config_io.repository_root``).
    """
    text = str(path)
    path = Path(path)
    # A bare name (no folder, no .toml) is a preset unless a file of that name stands here: a folder
    # named like a preset (e.g. the demo's output) must not hide it.
    bare = not any(separator in text for separator in ("/", os.sep)) and path.suffix.lower() != ".toml"
    if bare and not path.is_file():
        preset = CONFIG_DIR / "compare" / f"{text}.toml"
        if not preset.is_file():
            names = sorted(item.stem for item in (CONFIG_DIR / "compare").glob("*.toml"))
            raise InputError(f"no compare config {text} (a TOML file, or a preset: {', '.join(names)})")
        path = preset
    elif not path.exists():
        raise InputError(f"compare config not found: {text}")
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
