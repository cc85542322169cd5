"""The pattern sets a comparison measures (``Method``): heuristic families, learned and searched
patterns (run here, or reused from an earlier run of the same settings and input files), external
pattern files and the OLAT reference."""
from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path


from capture_sim.atomic import write_json
from capture_sim.errors import DisplexWarning, InputError
from patterns.families import get_family, make_patterns
from patterns.io import load_patterns
from train.compare_config import CompareConfig, SearchRun
from train.config_io import changed_keys, config_to_dict
from train.learn import TrainConfig, auto_init_family, changed_files, initial_patterns, input_fingerprints, train_patterns
from train.search import check_search_setup, run_search, trace_chart_path



@dataclass(eq=False)
class Method:
    """One pattern set in the comparison (mutable record filled during the run).

    Attributes:
        id: unique key, e.g. ``heuristic_tri_complementary_M2`` or ``learned_M4_seed1``.
        kind: "heuristic", "learned", "rerender" (learned with the re-rendering loss), "search",
            "external" or "reference".
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


def _finished(path: Path) -> bool:
    """Whether the run that writes ``path`` finished: its run record, written after the pattern
    file, exists. A stop between the two leaves a pattern file the run must write again (a
    learning run resumes from its last checkpoint, a search starts over)."""
    return path.exists() and _record_path(path).exists()


def _record_path(path: Path) -> Path:
    return path.with_name(path.stem + ".run.json")


def _reusable(path: Path, run_config, what: str) -> dict | None:
    """Meta and patterns of a finished run's output (``_finished``) made with the same config (a
    TrainConfig or SearchConfig) from the same input files; None if absent or unfinished. Another
    config, or input files that changed since (``train.learn.input_fingerprints``: scene, init
    pattern and rig files), raise."""
    if not _finished(path):
        return None
    reason = _stale_reason(path, run_config)
    if reason is not None:
        raise InputError(f"{path} holds {what} {reason}; delete it or choose another output folder")
    patterns, meta = load_patterns(path)
    return {"meta": meta, "patterns": patterns}


_COMPARE_NAMES = {"scenes": "train_scenes", "val_scenes": "test_scenes (the learning runs' validation)",
                  "noise_scale": "default_noise", "num_patterns": "M"}
"""The comparison's names of the run settings it sets itself (TrainConfig / SearchConfig fields);
the others come from its [learned], [learned_at.M] or [[search]] tables under their own names."""


def _stale_reason(path: Path, run_config) -> str | None:
    """Why the existing output ``path`` cannot stand for a run of ``run_config``, or None."""
    _, meta = load_patterns(path)
    recorded_config, wanted = meta.get("config"), config_to_dict(run_config)
    if recorded_config != wanted:
        # A learning run's val_scenes are the test scenes, its scenes the training scenes: a
        # changed scene list shows there.
        changed = [_COMPARE_NAMES.get(key, key) for key in changed_keys(recorded_config, wanted)]
        return "made with another config" + (f" (settings that differ: {', '.join(changed)})" if changed else "")
    # Records of earlier versions held the scene files only: such a run cannot show it was made
    # from the current rig and init files, so it is not reused.
    recorded, current = _run_record(path).get("input_files"), input_fingerprints(run_config)
    if recorded != current:
        return f"made from input files (scenes, rig or init patterns) that were rewritten, replaced or touched since{changed_files(recorded or [], current)}, or not recorded"
    return None


def _run_record(path: Path) -> dict:
    record = _record_path(path)
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
    before it. Every such output is named in one message (after a rig file changed, all are)."""
    runs = [_learned_output(config, count, seed, rerender, pattern_dir)[1:] for count, seed, rerender in _learning_runs(config)]
    runs += [(pattern_dir / f"{run.name}.npz", config.search_config(run)) for run in config.search]
    stale = [(path, reason) for path, run_config in runs if _finished(path) and (reason := _stale_reason(path, run_config)) is not None]
    if len(stale) == 1:
        raise InputError(f"{stale[0][0]} holds patterns {stale[0][1]}; delete it or choose another output folder")
    if stale:
        listed = "; ".join(f"{path.name}: {reason}" for path, reason in stale)
        raise InputError(f"{len(stale)} earlier runs in {pattern_dir} cannot be reused ({listed}); delete them or choose another output folder")


def _check_run_starts(config: CompareConfig, rig) -> None:
    """Refuse, before any learning starts, a learning start (family or pattern file) that does not
    fit its M and the rig's grid, and a search whose family does not support its M there or has
    more parameters than its algorithm takes: each run checks itself, but only when its turn comes,
    after minutes of the runs before it."""
    for count, seed, rerender in _learning_runs(config):
        initial_patterns(config.train_config(count, seed, rerender), rig.rows, rig.cols)
    for run in config.search:
        check_search_setup(config.search_config(run), rig)


def learned_method(config: CompareConfig, num_patterns: int, seed: int, pattern_dir: Path, progress: bool,
                   rerender: bool = False, logdir: Path | None = None) -> Method:
    """Learn (or reuse) the patterns of one learning run (``rerender``: with the re-rendering loss).

    TensorBoard logs of a new run go to ``logdir/<method id>`` when ``logdir`` is given.
    """
    method_id, path, train_config = _learned_output(config, num_patterns, seed, rerender, pattern_dir)
    existing = _reusable(path, train_config, "learned patterns")
    if existing is None:
        _record_path(path).unlink(missing_ok=True)  # an earlier run's record must not vouch for this run's file
        result = train_patterns(train_config, path, logdir=None if logdir is None else logdir / method_id, progress=progress,
                                checkpoint_mode="resume_or_fresh", own_logdir=True)
        seconds = result.seconds  # includes the sessions of a resumed run
        write_json(_record_path(path), {"seconds": seconds, "steps": train_config.steps, "input_files": input_fingerprints(train_config)})
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
        _record_path(path).unlink(missing_ok=True)
        meta = run_search(search_config, path, logdir=None if logdir is None else logdir / run.name, progress=progress, own_logdir=True)
        patterns, seconds = load_patterns(path)[0], meta["seconds"]
        write_json(_record_path(path), {"seconds": seconds, "input_files": input_fingerprints(search_config)})
    else:
        meta, patterns = existing["meta"], existing["patterns"]
        seconds = _run_record(path).get("seconds")
    info = {key: meta[key] for key in ("start_mae", "best_mae", "evaluations", "stop_reason", "sharpness")}
    info["parameters"] = len(meta.get("parameter_names", ()))
    info["trace_png"] = str(trace_chart_path(path))
    return Method(run.name, "search", f"search:{run.family}:{run.algorithm}", f"{run.family} + {run.algorithm}", run.num_patterns,
                  patterns, str(path), seconds, info=info)


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
    _check_run_starts(config, rig)
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
            except InputError as error:  # identical or flat patterns on a small grid: a skip, like an unsupported M
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
