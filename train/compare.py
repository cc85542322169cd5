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
charts (``train.report``, ``train.report_charts``), and the learned / searched / heuristic pattern files in ``patterns/``.
A rerun with the same out folder reuses learned and searched pattern files whose config matches.
The settings are ``train.compare_config``'s; the pattern sets are collected (learned, searched,
reused) by ``train.compare_methods``; this module measures them and writes the outputs.
"""
from __future__ import annotations

import ctypes
import dataclasses
import json
import math
import multiprocessing
import multiprocessing.connection
import os
import signal
import time
import warnings
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from capture_sim.atomic import refuse_overwriting, staged_files, write_json
from capture_sim.display import display_emission
from capture_sim.errors import DisplexWarning, InputError
from capture_sim.rig import CONFIG_DIR, DEFAULT_RIG, load_rig
from capture_sim.scene import scene_files, scene_paths
from capture_sim.synth import GENERATOR
from patterns.io import names_pattern_file, save_patterns
from train.capture import scene_exposure
from train.compare_config import CompareConfig, compare_config_to_dict, load_compare_config, rig_exposure_ms
from train.compare_methods import Method, collect_methods
from train.evaluate import EvalSettings, evaluate_scene
from train.learn import tensorboard_folder_name
from train.rig_choice import rig_for_inputs, warn_other_rigs
from train.scene_pixels import ScenePixels, fixed_pixel_subsets, scene_pixels
from train.scene_sets import resolve_scenes

SUMMARY_METRICS = ("mae", "median", "under_5", "under_10", "under_20", "under_30", "invalid_fraction", "exposure", "seconds", "reconstruct_seconds")
"""Per-scene metrics averaged over the test scenes (each scene weighs the same)."""


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
        ``simulate_reconstruct_seconds``: simulation plus reconstruction wall time per scene;
        ``reconstruct_seconds``: the reconstruction's alone, the compute time the report charts),
        ``capture_seconds`` (the scene mean of M x exposure_ms x e / e_white, in seconds),
        ``flagged`` (flag name -> the scene mean of the share of pixels carrying it), and the
        per-scene values under ``scenes``.
    """
    summary = {key: float(np.mean([metrics[key] for metrics in scene_metrics])) for key in SUMMARY_METRICS}
    summary["simulate_reconstruct_seconds"] = summary.pop("seconds")
    captures = [num_patterns * exposure_ms / 1000.0 * metrics["exposure"] / white for metrics, white in zip(scene_metrics, white_exposures, strict=True)]
    summary["capture_seconds"] = float(np.mean(captures))
    summary["flagged"] = {name: float(np.mean([metrics["flagged"][name] for metrics in scene_metrics])) for name in scene_metrics[0]["flagged"]}
    summary["scenes"] = [{**{key: metrics[key] for key in ("name", "mae", "median", "invalid_fraction", "exposure", "seconds", "reconstruct_seconds")}, "capture_seconds": capture}
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


PR_SET_PDEATHSIG = 1
"""Linux prctl option: the signal the kernel sends a process when its parent exits."""


def _init_worker(parent: int) -> None:
    # Forked children must not enter the parent's OpenMP pool (as torch's DataLoader workers).
    torch.set_num_threads(1)
    # Ctrl-C reaches the whole process group: the parent stops the workers (``_evaluate_in_workers``).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # A worker ends quietly on SIGTERM, not with the parent's clean-up (``train.cli.Terminated``).
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    # A parent that dies without stopping its workers (SIGKILL, the OOM killer) takes them along:
    # on Linux the kernel kills them; elsewhere a worker stops before its next job (``_worker_main``).
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):  # no prctl (macOS) or no C library handle
        pass
    if os.getppid() != parent:  # the parent died before the kernel knew to tell
        os._exit(0)


def _evaluate_keyed(job: tuple) -> tuple:
    """``_evaluate_job`` of ``job`` = (key, patterns, reference, noise, exposures), returned with its key."""
    key, *arguments = job
    return key, _evaluate_job(*arguments)


def _worker_main(jobs: list, connection, parent: int) -> None:
    """A forked evaluation worker of the process ``parent``: runs its share of the jobs and sends
    ("result", (key, metrics)) per job, or ("error", exception) and stops; stops early if the
    parent is gone (its pipe may still have a reader: other workers inherit its read end)."""
    _init_worker(parent)
    try:
        for job in jobs:
            if os.getppid() != parent:
                return
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
    workers = min(workers, len(jobs))  # more would idle (and a huge setting would loop for ever)
    try:
        for index in range(workers):
            share = jobs[index::workers]
            receiver, sender = context.Pipe(duplex=False)
            process = context.Process(target=_worker_main, args=(share, sender, os.getpid()), daemon=True)
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
    """JSON record of one evaluated method (the pattern file's and a search trace chart's paths
    relative to ``out_dir`` when inside it; others as given)."""
    def inside(path):
        try:
            return str(Path(path).resolve().relative_to(out_dir.resolve()))
        except ValueError:
            return str(path)

    pattern_file = None if method.pattern_file is None else inside(method.pattern_file)
    info = dict(method.info)
    if "trace_png" in info:
        info["trace_png"] = inside(info["trace_png"])
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
        ``white_exposures`` (e_white per test scene, ``white_exposures``), ``white_exposures_olat``
        (the same in the OLAT reference's units), scene names, ``test_files_also_trained`` (test
        scene files that learning or searches also used), ``methods`` (each with ``evaluations`` per noise level), ``skipped``,
        ``summary`` (learned vs best heuristic, seed spread) and ``timings``.
    """
    from train.report import write_report
    from train.report_charts import CHARTS
    from train.report_rows import summary_tables

    out_dir = Path(out_dir)
    began = time.perf_counter()
    # A file where the folder goes, or a folder nothing can be written into: refused now, not
    # when the results are written after the work.
    pattern_dir = out_dir / "patterns"
    logs = bool(config.learned_pattern_counts() or config.rerender_counts or config.search)  # these log under tensorboard/
    fixed = [("results", out_dir / "results.json"), ("report", out_dir / "report.md"), ("config record", out_dir / "config.json"),
             *(("chart", out_dir / name) for name in CHARTS.values())]
    refuse_overwriting(fixed, [], folders=[("patterns folder", pattern_dir), ("tensorboard folder", out_dir / "tensorboard" if logs else None)])
    if logs:
        tensorboard_folder_name(out_dir, "compare output folder")
    if (pattern_dir / "__init__.py").exists():  # e.g. out = "." in the repository root
        raise InputError(f"compare output folder {out_dir} holds a Python package patterns/ (the source tree?), "
                         "into which compare would write its pattern files; choose another folder")
    pattern_inputs = [(f"[[external]] {item.name}:", item.path) for item in config.external]
    pattern_inputs += [("learned init pattern file", table["init"]) for table in (config.learned, *config.learned_at.values())
                       if names_pattern_file(table.get("init"))]
    for what, path in pattern_inputs:
        if Path(path).resolve().is_relative_to(pattern_dir.resolve()):
            raise InputError(f"{what} {path} lies in {pattern_dir}, whose files compare rewrites; "
                             "copy it elsewhere or choose another output folder")
    trained_test_files = _check_scene_lists(config)
    # Scenes made for another rig than the config's default need that rig; external pattern sets
    # made for another may be compared on purpose (transfer), with a warning.
    rig_for_inputs(None if config.rig == DEFAULT_RIG else config.rig, (), [*config.train_scenes, *config.test_scenes],
                   "the config's `rig` is the default", "set `rig` in the config to that rig's preset name or TOML file")
    rig = load_rig(config.rig)
    warn_other_rigs(rig, [item.path for item in config.external], "[[external]] pattern file")
    exposure_ms, exposure_source = rig_exposure_ms(rig)
    resolved = compare_config_to_dict(config)
    test_raw = resolve_scenes(tuple(config.test_scenes), "test", rig, config.scene_size, config.scene_seed)
    test_scenes = [scene_pixels(scene, rig, require_normals=True) for scene in test_raw]
    test_files = [scene.meta.get("file") for scene in test_raw]  # None for synthesised default scenes
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
        "white_exposures_olat": whites["olat"],  # the same in the units of the OLAT reference's gain
        "default_noise": config.default_noise,
        "noise_scales": [float(s) for s in config.noise_scales],
        "pattern_counts": list(config.pattern_counts),
        "test_scenes": [pixels.name for pixels in test_scenes],
        "test_scene_files": test_files,  # in the order of test_scenes: two files may carry one scene name
        "test_pixels": sum(pixels.num_pixels for pixels in test_scenes),
        "test_files_also_trained": trained_test_files,  # test scene files that learning or searches also used
        "test_image_sizes": sorted({f"{pixels.transport.height} x {pixels.transport.width}" for pixels in test_scenes}),
        "methods": [method_record(method, out_dir) for method in methods],
        "specular_free": specular_free,
        "skipped": skipped,
        "timings": timings,
        # Sums split across threads round differently: numbers can change in their last digits
        # with the thread count of this process (worker processes use one thread each).
        "threads": torch.get_num_threads(),
    }
    results["summary"] = summary_tables(results)
    results["timings"]["total_seconds"] = time.perf_counter() - began
    results["report"] = str(out_dir / "report.md")
    # The heuristic pattern files, report, charts, results and config are moved into place
    # together: a run refused or interrupted part-way leaves them all describing the last
    # finished run (learned and searched files are kept per settings, see ``train.compare_methods``).
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


def _check_scene_lists(config: CompareConfig) -> list[str]:
    """Refuse a test scene file listed twice (it would weigh twice in every mean); warn when a
    test scene is also a training scene of the learning or search runs (its MAE is not held out)
    and return the names of such files (the report says so too)."""
    test_files = [path.resolve() for path in scene_paths(config.test_scenes)]
    repeated = sorted({str(path) for path in test_files if test_files.count(path) > 1})
    if repeated:
        raise InputError(f"test_scenes name the same scene file twice: {', '.join(repeated)}")
    if config.learned_pattern_counts() or config.rerender_counts or config.search:
        shared = sorted(set(test_files) & {path.resolve() for path in scene_paths(config.train_scenes)})
        if shared:
            warnings.warn(f"{len(shared)} test scene(s) are also training scenes ({', '.join(path.name for path in shared)}): "
                          "their MAE is not measured on held-out scenes", DisplexWarning, stacklevel=2)
        return [path.name for path in shared]
    return []


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
    height, width = config.scene_size
    wanted = {"generator": GENERATOR, "rig": rig.name, "height": height, "width": width,
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
    present = {path.resolve() for split in splits for path in scene_files(folder / split)}
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
        height, width = config.scene_size
        write_scene_set(scene_dir, rig, height, width, config.scene_seed, progress=progress)
    # Absolute paths: the learned and searched runs record them in their configs, and a rerun
    # reuses those runs however --out is spelled and whatever the working directory.
    scene_dir = scene_dir.resolve()
    config = dataclasses.replace(config, train_scenes=(str(scene_dir / "train"),), test_scenes=(str(scene_dir / "test"),))
    results = run_compare(config, out_dir, progress)
    print(f"demo finished in {results['timings']['total_seconds']:.0f} s; report: {results['report']}")
    return results
