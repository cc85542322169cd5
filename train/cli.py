"""The `displex` command line: parses arguments and calls each command's ``run_*(config)``.

Bad input (``InputError``, a missing file) ends with one line on stderr and exit status 2; tests
call the ``run_*`` functions directly.
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import warnings
from contextlib import contextmanager
from pathlib import Path

from capture_sim.atomic import check_output_folder, refuse_overwriting, separate_json, strict_json
from capture_sim.errors import DisplexWarning, InputError, check_thread_count, forget_warnings, one_line
from capture_sim.rig import DEFAULT_RIG, rig_file

NOISE_CHOICES = ("off", "default")
NOISE_HELP = "'default': the rig's Poisson-Gaussian noise and quantisation; 'off': an ideal sensor (clipping stays)"
RIG_HELP = f"rig preset or TOML path (default {DEFAULT_RIG})"
INPUT_RIG_HELP = (f"rig preset or TOML path (default {DEFAULT_RIG}; without it, an input file made for another rig is "
                  "refused rather than used with the wrong display)")
EXPOSURE_HELP = "'rig' (default: the rig's exposure setting, auto for the presets), 'auto' or a positive gain"


def _size(text: str) -> tuple[int, int]:
    try:
        height, width = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 128x153, got {text!r}") from None
    if height < 2 or width < 2:
        raise argparse.ArgumentTypeError(f"size must be at least 2x2, got {text!r}")
    return height, width


class _UsageError(Exception):
    """A command line that argparse rejects (unknown flag, a number that is not one)."""


class _Parser(argparse.ArgumentParser):
    """argparse with one error line, like every other bad input: ``run`` prints it (argparse's own
    ``error`` prints the whole usage text and exits)."""

    def error(self, message):
        raise _UsageError(f"{self.prog}: {message} (see {self.prog} --help)")


def _path(text: str) -> Path:
    """A command-line path; an empty one is refused (Path('') would mean the current folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path")
    return Path(text)


def _file_output(text: str) -> Path:
    """A file to write: ``_path``, and one written as a folder ('x/', 'x/.', '.', 'x/..', or with
    '\\' on Windows) is refused here, where the text still says so (``Path`` drops a trailing '/'
    and '.': 'x/' became a file x)."""
    path = _path(text)
    separators = [separator for separator in (os.sep, os.altsep) if separator]  # '\\' and '/' on Windows
    if text in (".", "..") or text.endswith(tuple(separator + tail for separator in separators for tail in ("", ".", ".."))):
        raise argparse.ArgumentTypeError(f"{text} names a folder, not a file")
    return path


def _patterns_or_olat(text: str) -> str:
    """``--patterns`` of evaluate and invrender: 'olat' or a pattern file (an empty path is refused)."""
    if text != "olat":
        _path(text)
    return text


def _pattern_output(text: str) -> Path:
    """A pattern file to write, named .npz (``patterns.io.check_pattern_output``)."""
    from patterns.io import check_pattern_output

    path = _file_output(text)
    try:
        check_pattern_output(path)
    except InputError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return path


RERUN_REUSES_RUNS = ("rerun the same command to reuse its finished learning and search runs "
                     "(an interrupted learning run resumes from its checkpoint, an interrupted search starts again)")
"""What an interrupted compare or demo tells the user."""


def _thread_count(text: str) -> int:
    """``--threads T``, global or after ``invrender``; the range is ``check_thread_count``'s, which
    also checks ``InvRenderConfig.threads`` from Python."""
    try:
        count = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid thread count {text!r}") from None
    try:
        return check_thread_count(count)
    except InputError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _installed_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("displex")
    except PackageNotFoundError:  # run from a checkout that was never installed
        return "(not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="displex",
        description="Design illumination patterns for display-camera photometric stereo: synthesise scenes, "
        "simulate captures, reconstruct, learn and search patterns, export them, compare methods.",
    )
    parser.add_argument("--version", action="version", version=f"displex {_installed_version()}")
    parser.add_argument("--threads", type=_thread_count, default=0, dest="torch_threads", metavar="T",
                        help="torch threads for the command (default 0: torch's, one per core); 1 avoids the stalls of "
                        "torch's thread pool when other programs keep the cores busy, which can make commands 10x slower")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    scenes = commands.add_parser("scenes", help="synthetic scene sets").add_subparsers(dest="scenes_command", required=True, metavar="{synth}")
    synth = scenes.add_parser("synth", help="write the default synthetic scene set (train/ and test/ splits)")
    synth.add_argument("--out", type=_path, required=True, help="output folder")
    synth.add_argument("--size", type=_size, default=None, help="image size HxW (default: a quarter of the rig camera's, 128x153 on the reference rig, whose full size is 512x612)")
    synth.add_argument("--seed", type=int, default=0, help="seed of the scene set (shapes, materials, textures)")
    synth.add_argument("--rig", default=DEFAULT_RIG, help=RIG_HELP)
    synth.add_argument("--cast-shadows", action="store_true", help="trace cast shadows (slower)")
    synth.set_defaults(handler=_scenes_synth)

    simulate = commands.add_parser("simulate", help="simulate captures of a scene under a pattern set")
    simulate.add_argument("--scene", type=_path, required=True, help="scene file (.npz)")
    simulate.add_argument("--patterns", type=_path, required=True, help="pattern file .npz or .npy")
    simulate.add_argument("--out", type=_path, required=True, help="output folder: captures.npy, 16-bit PNGs, contact sheet, meta.json")
    simulate.add_argument("--noise", choices=NOISE_CHOICES, default="default", help=NOISE_HELP)
    simulate.add_argument("--exposure", default="rig", help=EXPOSURE_HELP)
    simulate.add_argument("--seed", type=int, default=0, help="seed of the simulated noise")
    simulate.add_argument("--rig", default=None, help=INPUT_RIG_HELP)
    simulate.set_defaults(handler=_simulate)

    patterns = commands.add_parser("patterns", help="heuristic pattern families").add_subparsers(dest="patterns_command", required=True, metavar="{make,list}")
    make = patterns.add_parser("make", help="write a heuristic pattern set")
    make.add_argument("--family", required=True, help="family name (see `displex patterns list`)")
    make.add_argument("--M", type=int, required=True, dest="num_patterns", help="number of patterns")
    make.add_argument("--out", type=_pattern_output, required=True, help="pattern file to write (.npz)")
    make.add_argument("--preset", default="default", help="'default' (off level 0, on level 1) or 'ddps' (the published 0.1/0.9 levels; tri_gradient keeps its published 0/1 levels in both, and the random families have no levels)")
    make.add_argument("--seed", type=int, default=None, help="seed of the random families (default 0; the other families draw nothing)")
    make.add_argument("--rig", default=DEFAULT_RIG, help=RIG_HELP)
    make.set_defaults(handler=_patterns_make)
    listing = patterns.add_parser("list", help="list families and their parameters")
    listing.add_argument("--M", type=int, default=4, dest="num_patterns", help="pattern count whose parameters are listed (default: 4)")
    listing.add_argument("--rig", default=DEFAULT_RIG, help=RIG_HELP + " (its grid decides which M a family supports)")
    listing.set_defaults(handler=_patterns_list)

    evaluate = commands.add_parser("evaluate", help="reconstruct scenes under a pattern set and measure normal errors")
    evaluate.add_argument("--scenes", type=_path, nargs="+", default=(), help="scene files or folders (default: synthetic test split)")
    evaluate.add_argument("--patterns", type=_patterns_or_olat, required=True, help="pattern file, or 'olat' for the full OLAT stack")
    evaluate.add_argument("--method", choices=("ps", "woodham"), default="ps", help="ps: analytic multiplexed photometric stereo (default); woodham: least squares per colour channel (OLAT or grey patterns)")
    evaluate.add_argument("--noise", choices=NOISE_CHOICES, default="default", help=NOISE_HELP)
    evaluate.add_argument("--exposure", default="rig", help=EXPOSURE_HELP)
    evaluate.add_argument("--rig", default=None, help=INPUT_RIG_HELP)
    evaluate.add_argument("--seed", type=int, default=0, help="seed of the simulated noise")
    evaluate.add_argument("--json", type=_file_output, default=None, help="write results JSON here")
    evaluate.add_argument("--out", type=_path, default=None, help="folder for normal maps, error maps, summary figure")
    evaluate.set_defaults(handler=_evaluate)

    train = commands.add_parser("train", help="learn patterns end to end through the photometric stereo")
    train.add_argument("--config", type=_path, default=None, help="settings file (TOML, e.g. configs/train/default.toml); flags override it")
    train.add_argument("--M", type=int, dest="num_patterns", default=None, help="number of patterns to learn (default: the config's, 4)")
    train.add_argument("--init", default=None, help="family name or pattern file to start from")
    train.add_argument("--scenes", type=_path, nargs="+", default=None, help="training scenes (default: synthetic train split)")
    train.add_argument(
        "--val-scenes", type=_path, nargs="+", default=None, help="validation scenes (default: the synthetic test split with the default training scenes, none with --scenes)"
    )
    train.add_argument("--steps", type=int, default=None, help="Adam steps (default: the config's; configs/train/default.toml: 150)")
    train.add_argument("--seed", type=int, default=None, help="seed of the start, pixel sampling and noise (default: the config's, 0)")
    train.add_argument("--rig", default=None, help="rig preset or TOML path (default: the config's, " + DEFAULT_RIG + ")")
    train.add_argument("--logdir", type=_path, default=None, help="TensorBoard log folder")
    train.add_argument("--rerender-weight", type=float, default=None, help="weight of the re-rendering loss (0 = normals only)")
    train.add_argument("--out", type=_pattern_output, required=True, help="learned pattern file (.npz)")
    train.add_argument("--fresh", action="store_true", help="start afresh: delete the checkpoint of --out instead of resuming it")
    train.set_defaults(handler=_train, interrupted=_train_interrupted)

    search = commands.add_parser("search", help="NLopt search over a heuristic family's parameters")
    search.add_argument("--config", type=_path, default=None, help="settings file (TOML, e.g. configs/search/default.toml); flags override it")
    search.add_argument("--family", default=None, help="family name (see `displex patterns list`); default: the config's")
    search.add_argument("--M", type=int, dest="num_patterns", default=None, help="number of patterns; default: the config's")
    search.add_argument("--algorithm", default=None, help="LN_BOBYQA (default), LN_COBYLA, LN_SBPLX, GN_CRS2_LM, GN_ESCH, GN_DIRECT_L, LD_MMA, LD_LBFGS")
    search.add_argument("--maxeval", type=int, default=None, help="largest number of objective evaluations")
    search.add_argument("--maxtime", type=float, default=None, help="wall-clock limit in seconds (0 = none)")
    search.add_argument("--seed", type=int, default=None, help="seed of NLopt's random choices, the pixel subsets and the noise (default: the config's, 0)")
    search.add_argument("--scenes", type=_path, nargs="+", default=None, help="scenes to optimise on (default: synthetic train split)")
    search.add_argument("--rig", default=None, help="rig preset or TOML path (default: the config's, " + DEFAULT_RIG + ")")
    search.add_argument("--logdir", type=_path, default=None, help="TensorBoard folder: MAE and best-so-far per evaluation")
    search.add_argument("--out", type=_pattern_output, required=True,
                        help="best pattern file; the trace goes to <stem>.trace.csv and .trace.png (<stem>.trace.partial.csv while it runs)")
    search.set_defaults(handler=_search, interrupted=_search_interrupted)

    compare = commands.add_parser("compare", help="compare learned, searched, heuristic and external patterns on held-out scenes")
    compare.add_argument("--config", type=_path, required=True, help="settings file (TOML, anywhere; e.g. configs/compare/demo.toml), or a preset name: default, demo")
    compare.add_argument("--out", type=_path, default=None, help="output folder (default: the config's `out`, relative to the folder holding the config's configs/)")
    compare.set_defaults(handler=_compare, interrupted=RERUN_REUSES_RUNS)

    export = commands.add_parser("export", help="write display frames, manifest and contact sheet for the rig")
    export.add_argument("--patterns", type=_path, required=True, help="pattern file .npz or .npy, values in [0, 1]")
    export.add_argument("--rig", default=None, help=INPUT_RIG_HELP)
    export.add_argument("--out", type=_path, required=True, help="output folder for the frames, manifest.json and contact sheet")
    export.add_argument("--bit-depth", type=int, choices=(8, 16), default=8, help="bits per channel of the PNG frames (default: 8)")
    export.add_argument("--olat", action="store_true", help="also write the OLAT capture sequence (K frames, black, white)")
    export.set_defaults(handler=_export)

    import_frames = commands.add_parser("import-frames", help="recover patterns from exported frames")
    import_frames.add_argument("frames", type=_path, help="folder written by `displex export`")
    import_frames.add_argument("--out", type=_pattern_output, required=True, help="pattern file to write (.npz)")
    import_frames.set_defaults(handler=_import_frames)

    invrender = commands.add_parser("invrender", help="baseline inverse renderer: normals, basis BRDFs, relighting")
    invrender.add_argument("--scene", type=_path, required=True, help="scene file (.npz)")
    invrender.add_argument("--patterns", type=_patterns_or_olat, default="olat", help="pattern file, or 'olat' (fit on 5/6 of the OLAT images; the default)")
    invrender.add_argument("--basis", default="auto", help="number of basis BRDFs J, or 'auto' (model selection; the default)")
    invrender.add_argument("--iterations", type=int, default=None, help="Adam steps of the final fit (default 400)")
    invrender.add_argument("--noise", choices=NOISE_CHOICES, default="default", help=NOISE_HELP)
    invrender.add_argument("--exposure", default="rig", help=EXPOSURE_HELP + " (with --patterns; OLAT captures are always auto-exposed)")
    invrender.add_argument("--seed", type=int, default=0, help="seed of the simulated noise")
    invrender.add_argument("--rig", default=None, help=INPUT_RIG_HELP)
    # The global --threads, also accepted here (older command lines). SUPPRESS: without this flag a
    # global value stands (a subcommand default would overwrite it).
    invrender.add_argument("--threads", type=_thread_count, default=argparse.SUPPRESS, dest="torch_threads", metavar="T",
                           help="same as `displex --threads T invrender ...`")
    invrender.add_argument("--json", type=_file_output, default=None, help="write the result JSON here")
    invrender.add_argument("--out", type=_path, default=None, help="folder for normals, basis weights, figures, result.json, config.json and TensorBoard logs")
    invrender.set_defaults(handler=_invrender)

    demo = commands.add_parser("demo", help="the main job: scenes, learning, search, comparison, report and charts")
    demo.add_argument("--out", type=_path, default=Path("runs/demo"), help="output folder: scenes, report.md, results.json, charts, patterns (default: runs/demo)")
    demo.add_argument("--steps", type=int, default=None, help="learning steps of every learned pattern set (default: 150, and 100 at M = 10, as configs/compare/demo.toml sets them)")
    demo.set_defaults(handler=_demo, interrupted=RERUN_REUSES_RUNS)

    bench = commands.add_parser("bench", help="benchmarks written as JSON (medians of several runs)")
    bench.add_argument("target", help="what to benchmark: sim, ps, train (about a minute each), invrender (a few minutes)")
    bench.add_argument("--json", type=_file_output, default=None, help="write the results here")
    bench.add_argument("--repeats", type=int, default=None, help="timed runs per measurement, whose median is reported (default: 5; not with --sweep, which times nothing)")
    bench.add_argument(
        "--sweep", action="store_true", help="with target ps: normal error against noise level for several methods (JSON and a chart next to it)"
    )
    bench.add_argument("--size", type=_size, default=None, help="image size HxW of the --sweep scenes (default 128x153)")
    bench.set_defaults(handler=_bench)

    return parser


def _evaluate(args) -> None:
    from train.evaluate_command import EvaluateConfig, run_evaluate

    if args.out is not None:
        check_output_folder(args.out, "evaluate")
    rig = rig_for_inputs(args.rig, [args.patterns], args.scenes)
    config = EvaluateConfig(tuple(args.scenes), args.patterns, args.method, args.noise, args.exposure, rig, args.seed, args.json, args.out)
    document = run_evaluate(config)
    for row in document["scenes"]:
        print(f"{row['name']:<32} MAE {row['mae']:6.2f} deg  median {row['median']:6.2f}  invalid {row['invalid_fraction']:.3f}")
    print(f"mean MAE {document['mean_mae']:.2f} deg")


def _flag_names(overrides: dict, **special: str) -> dict:
    """Config field -> the flag that sets it (``rerender_weight`` -> ``--rerender-weight``)."""
    return {key: special.get(key, "--" + key.replace("_", "-")) for key in overrides}


def _train(args) -> None:
    from train.config_io import load_config
    from train.learn import TrainConfig, checkpoint_path, names_pattern_file, output_files, train_patterns

    args.earlier_checkpoint = _file_stamp(checkpoint_path(args.out))  # for the Ctrl-C hint of a --fresh run

    overrides = {
        "num_patterns": args.num_patterns,
        "init": args.init,
        "scenes": None if args.scenes is None else tuple(str(p) for p in args.scenes),
        "val_scenes": None if args.val_scenes is None else tuple(str(p) for p in args.val_scenes),
        "steps": args.steps,
        "seed": args.seed,
        "rerender_weight": args.rerender_weight,
        "rig": args.rig,
    }
    config = load_config(TrainConfig, args.config, overrides, flags=_flag_names(overrides, num_patterns="--M"))
    _check_default_rig(config.rig, args.rig, [config.init if names_pattern_file(config.init) else None], [*config.scenes, *config.val_scenes])
    refuse_overwriting(output_files(args.out), [("--init file", config.init), ("--config file", args.config),
                                                *_scene_files(config.scenes, config.val_scenes)])
    _refuse_out_among_scenes(args.out, config.scenes, config.val_scenes)
    result = train_patterns(config, args.out, logdir=args.logdir, checkpoint_mode="fresh" if args.fresh else "resume")
    last = f", validation MAE {result.val_history[-1][1]:.2f} deg" if result.val_history else " (not validated: pass --val-scenes)"
    print(f"wrote learned patterns to {args.out}{last}")


def rig_for_inputs(given: str | None, pattern_files=(), scenes=(), unchosen: str = "no --rig was given") -> str:
    """``train.rig_choice.rig_for_inputs``, imported when a command runs (it loads torch)."""
    from train.rig_choice import rig_for_inputs as choose

    return choose(given, pattern_files, scenes, unchosen)


def _check_default_rig(rig: str, flag: str | None, pattern_files, scenes) -> None:
    """``rig_for_inputs`` for commands whose rig may also come from a config: a config that names
    a rig other than the default has chosen, as --rig does."""
    rig_for_inputs(None if flag is None and rig == DEFAULT_RIG else rig, pattern_files, scenes,
                   "neither --rig nor the config's `rig` named another")


def _refuse_out_among_scenes(out: Path, *groups) -> None:
    """Refuse a pattern file written into a folder given as scenes: every later command reading
    that folder would take it for a scene (and refuse it)."""
    if Path(out).suffix != ".npz":  # scene folders are read with a case-sensitive *.npz
        return
    folder = Path(out).resolve().parent
    for paths in groups:
        for entry in paths or ():
            if Path(entry).is_dir() and Path(entry).resolve() == folder:
                raise InputError(f"--out {out} lies in the scene folder {entry}, where later commands would read it as a scene; "
                                 "write it elsewhere")


def _scene_files(*groups):
    """("scene", file) input pairs for ``refuse_overwriting`` from lists of scene paths (files, or
    folders, whose .npz files are what an output must not replace)."""
    from capture_sim.scene import scene_paths

    for paths in groups:
        for scene in scene_paths(paths or ()):
            yield "scene", scene


def _train_interrupted(args) -> str:
    from train.learn import checkpoint_path

    checkpoint = checkpoint_path(args.out)
    # With --fresh the same command starts afresh: an earlier run's checkpoint is not this one's.
    earlier = args.fresh and (not hasattr(args, "earlier_checkpoint") or _file_stamp(checkpoint) == args.earlier_checkpoint)
    if not checkpoint.exists() or earlier:
        return "no checkpoint was written yet; rerun the same command to start again"
    rerun = "rerun it without --fresh" if args.fresh else "rerun the same command"
    return f"{rerun} to resume from its last checkpoint, {checkpoint}"


def _search_interrupted(args) -> str:
    from train.search import partial_trace_path

    partial = partial_trace_path(args.out)
    if not partial.exists():
        return "no evaluation was made yet"
    # The search removes an earlier interrupted run's partial trace only once its inputs are
    # checked; interrupted before ``_search`` took the file's stamp, no evaluation was made.
    if not hasattr(args, "earlier_partial") or _file_stamp(partial) == args.earlier_partial:
        return f"no evaluation was made yet; an earlier run's evaluations are still in {partial}"
    return f"the evaluations made so far are in {partial}"


def _file_stamp(path: Path) -> tuple[int, int] | None:
    """(inode, modification time in ns) of an existing file, None if there is none."""
    try:
        status = path.stat()
    except OSError:
        return None
    return status.st_ino, status.st_mtime_ns


def _search(args) -> None:
    from train.config_io import load_config
    from train.search import SearchConfig, output_files, partial_trace_path, run_search, start_text

    args.earlier_partial = _file_stamp(partial_trace_path(args.out))  # for the Ctrl-C hint
    overrides = {
        "family": args.family,
        "num_patterns": args.num_patterns,
        "algorithm": args.algorithm,
        "maxeval": args.maxeval,
        "maxtime": args.maxtime,
        "seed": args.seed,
        "scenes": None if args.scenes is None else tuple(str(p) for p in args.scenes),
        "rig": args.rig,
    }
    config = load_config(SearchConfig, args.config, overrides, flags=_flag_names(overrides, num_patterns="--M"))
    _check_default_rig(config.rig, args.rig, [], config.scenes)
    refuse_overwriting(output_files(args.out), [("--config file", args.config), *_scene_files(config.scenes)])
    _refuse_out_among_scenes(args.out, config.scenes)
    summary = run_search(config, args.out, logdir=args.logdir)
    print(f"{summary['family']} M={summary['num_patterns']} {summary['algorithm']}: MAE {summary['start_mae']:.2f} "
          f"({start_text(summary['start'], summary['sharpness'])}) -> "
          f"{summary['best_mae']:.2f} deg in {summary['evaluations']} evaluations ({summary['stop_reason']}); trace {summary['trace_csv']}")


def _compare(args) -> None:
    from train.compare import run_compare
    from train.compare_config import load_compare_config

    config = load_compare_config(args.config)
    results = run_compare(config, args.out if args.out is not None else Path(config.out))
    print(f"compared {len(results['methods'])} pattern sets in {results['timings']['total_seconds']:.0f} s; report: {results['report']}")


def _export(args) -> None:
    from capture_sim.rig import load_rig
    from patterns.export import export_frames, replaced_by_export
    from patterns.io import load_patterns

    if replaced_by_export(args.patterns, args.out):
        raise InputError(f"--patterns {args.patterns} lies in the export folder under a name the export replaces; move it or choose another --out")
    values, _ = load_patterns(args.patterns)
    rig = load_rig(rig_for_inputs(args.rig, [args.patterns]))
    manifest = export_frames(values, rig, args.out, bit_depth=args.bit_depth, include_olat=args.olat)
    print(f"wrote {len(manifest['frames'])} frames and manifest.json to {args.out}")


def _import_frames(args) -> None:
    from patterns.export import CONTACT_SHEET_NAME, MANIFEST_NAME, import_frames
    from patterns.io import save_patterns

    values, manifest = import_frames(args.frames)
    frames = [("manifest", args.frames / MANIFEST_NAME), ("contact sheet", args.frames / CONTACT_SHEET_NAME)]
    frames += [("frame", args.frames / frame["file"]) for frame in manifest["frames"]]
    refuse_overwriting([("--out", args.out)], frames)
    save_patterns(args.out, values, {"family": "imported", "made_by": "displex import-frames", "source": str(args.frames), "rig": manifest.get("rig")})
    print(f"recovered {len(values)} patterns from {args.frames} into {args.out}")


def _invrender(args) -> None:
    from train.invrender_command import OUTPUT_FILES, InvRenderConfig, run_invrender

    if args.out is not None:
        check_output_folder(args.out, "invrender")
    outputs = [("--json", separate_json(args.json, args.out, "result.json")), *((f"--out file {name}", None if args.out is None else args.out / name) for name in OUTPUT_FILES)]
    refuse_overwriting(outputs, [("--scene", args.scene), ("--patterns file", None if args.patterns == "olat" else args.patterns),
                                 ("--rig file", None if args.rig is None else rig_file(args.rig))], folders=[("--out", args.out)])
    args.rig = rig_for_inputs(args.rig, [args.patterns], [args.scene])
    changes = dict(scene=args.scene, patterns=args.patterns, basis=args.basis, noise=args.noise, seed=args.seed, rig=args.rig, json=args.json, out=args.out,
                   threads=args.torch_threads, exposure=args.exposure)  # already applied by _run; recorded in config.json
    if args.iterations is not None:
        changes["iterations"] = args.iterations
    document = run_invrender(InvRenderConfig(**changes))
    print(strict_json({key: document[key] for key in ("mae", "psnr", "ssim", "seconds", "cpu_seconds", "J") if key in document}, indent=2))


def _demo(args) -> None:
    from train.compare import run_demo

    if args.steps is not None and args.steps < 0:
        raise InputError("--steps must be >= 0")
    run_demo(args.out, steps=args.steps)


def _bench(args) -> None:
    from train.bench import run_bench

    if args.repeats is not None and args.repeats < 1:
        raise InputError("--repeats must be at least 1")
    if args.repeats is not None and args.sweep:
        raise InputError("--repeats applies to the timing benchmarks, not --sweep (its errors are computed once, from seeded noise)")
    if args.size is not None and not args.sweep:
        raise InputError("--size applies to --sweep only (the timing benchmarks use the full 512 x 612 frame)")
    if args.sweep:
        if args.target != "ps":
            raise InputError(f"--sweep applies to target ps, not {args.target!r}")
        from train.bench import run_sweep

        # The chart goes next to the JSON, same name, .png; both are checked before the work. A
        # JSON named .PNG would be its chart on a case-insensitive file system, which path
        # comparison cannot see.
        if args.json is not None and args.json.suffix.lower() == ".png":
            raise InputError(f"--json {args.json}: the sweep writes its chart under that name (.png); name the JSON .json")
        refuse_overwriting([("--json", args.json), ("chart", None if args.json is None else args.json.with_suffix(".png"))], [])
        document = run_sweep(args.json, args.size)
        for row in document["methods"]:
            print(f"{row['label']:36s} " + "  ".join(f"{scale:g}: {mae:.3f}" for scale, mae in zip(document["noise_scales"], row["mae"])))
        if args.json is not None:
            print(f"wrote {args.json} and {args.json.with_suffix('.png')}")
        return
    refuse_overwriting([("--json", args.json)], [])  # before minutes of timing, not after
    print(strict_json(run_bench(args.target, args.json, 5 if args.repeats is None else args.repeats), indent=2))


def _scenes_synth(args) -> None:
    from capture_sim.rig import load_rig
    from capture_sim.synth import write_scene_set

    check_output_folder(args.out, "scenes synth")
    height, width = (None, None) if args.size is None else args.size
    index_path = write_scene_set(args.out, rig=load_rig(args.rig), height=height, width=width, seed=args.seed, cast_shadows=args.cast_shadows)
    print(f"wrote the scene set to {args.out} (index: {index_path})")


def _simulate(args) -> None:
    from train.simulate_command import SimulateConfig, run_simulate

    rig = rig_for_inputs(args.rig, [args.patterns], [args.scene])
    meta = run_simulate(SimulateConfig(args.scene, args.patterns, args.out, args.noise, args.exposure, args.seed, rig))
    print(f"wrote {len(meta['files'])} captures to {args.out} (exposure {meta['exposure']:.4g})")


def _patterns_make(args) -> None:
    from capture_sim.rig import load_rig
    from patterns.families import get_family, make_patterns
    from patterns.io import save_patterns

    refuse_overwriting([("--out", args.out)], [("--rig file", args.rig)])
    rig = load_rig(args.rig)
    seed = 0 if args.seed is None else args.seed
    values = make_patterns(args.family, args.num_patterns, rows=rig.rows, cols=rig.cols, preset=args.preset, seed=seed)
    family = get_family(args.family)
    if family.values_are_parameters:  # listing them would make the meta several times the values' size
        parameters = f"the {values.numel()} pattern values (family, seed and preset reproduce them)"
        drawn = {"seed": seed}
    else:
        parameters = {p.name: p.default for p in family.parameters(args.num_patterns, rig.rows, rig.cols, args.preset, seed)}
        drawn = {}  # a seed the values do not depend on is not recorded as if they did
        if args.seed is not None:
            warnings.warn(f"--seed has no effect on family {args.family}: only the random families draw values", DisplexWarning, stacklevel=2)
    save_patterns(args.out, values, {"family": args.family, "preset": args.preset, **drawn, "rig": rig.name,
                                     "parameters": parameters, "made_by": "displex patterns make"})
    print(f"wrote {args.family} M={args.num_patterns} to {args.out}")


def _patterns_list(args) -> None:
    from capture_sim.rig import load_rig
    from patterns.families import FAMILIES, make_patterns

    if args.num_patterns < 1:
        raise InputError(f"--M must be at least 1, got {args.num_patterns}")
    rig = load_rig(args.rig)
    for name, family in FAMILIES.items():
        if not family.supports(args.num_patterns, rig.rows, rig.cols):
            print(f"{name:<20} (not defined for M={args.num_patterns} on {rig.rows} x {rig.cols}) {family.summary}")
            continue
        try:  # the count rule allows it, but on a small grid patterns may repeat others or be flat
            make_patterns(name, args.num_patterns, rig.rows, rig.cols)
        except InputError as error:
            reason = "identical patterns" if "identical patterns" in str(error) else "flat patterns: a single row or column across a direction"
            print(f"{name:<20} ({reason} for M={args.num_patterns} on {rig.rows} x {rig.cols}) {family.summary}")
            continue
        names = ", ".join(parameter.name for parameter in family.parameters(args.num_patterns, rig.rows, rig.cols))
        print(f"{name:<20} {family.summary}\n{'':<20} parameters at M={args.num_patterns}: {names[:160]}{'...' if len(names) > 160 else ''}")


def _show_warning(message, category, filename, lineno, file=None, line=None, _default=warnings.showwarning):
    if issubclass(category, DisplexWarning):
        from tqdm import tqdm

        tqdm.write(f"displex: warning: {one_line(message)}", file=sys.stderr)  # on its own line, above any progress bar
    else:
        _default(message, category, filename, lineno, file, line)


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a job scheduler, ``docker stop``), raised where a Ctrl-C
    would be: the same clean-up runs (staging folders, evaluation workers, a search's partial
    trace) and the same resume hint is printed."""


def _raise_terminated(_number, _frame):
    raise Terminated()


@contextmanager
def _sigterm_as_interrupt():
    """SIGTERM raises ``Terminated`` for the block, unless someone else set its handler (``run``
    called in-process by a program with its own) or this is not the main thread (where Python
    cannot set handlers); without it the process died at once, its clean-up skipped."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _interrupted_status(interrupt: KeyboardInterrupt) -> tuple[str, int]:
    """('interrupted', 130) for a Ctrl-C, ('terminated', 143) for SIGTERM: the shell's statuses."""
    return ("terminated", 143) if isinstance(interrupt, Terminated) else ("interrupted", 130)


def run(argv: list[str] | None = None) -> int:
    """Run one command; returns 0 on success, 2 on bad input (after printing one error line), 130
    when interrupted by Ctrl-C and 143 by SIGTERM (one line; commands that resume say how)."""
    forget_warnings()  # each command says each of its warn_once messages once
    # Under a strict stdout (e.g. en_US.UTF-8), a path that is not valid UTF-8 would fail its
    # report line after the command's work: it is printed escaped instead, as on stderr, and the
    # stream is restored afterwards (run is also called in-process).
    stdout = sys.stdout
    relaxed = False
    if getattr(stdout, "errors", None) == "strict" and hasattr(stdout, "reconfigure"):
        try:
            stdout.reconfigure(errors="backslashreplace")
            relaxed = True
        except (OSError, ValueError):  # io.UnsupportedOperation: a stream already read from
            pass
    with warnings.catch_warnings():  # restores the warning hook afterwards (run is also called in-process)
        warnings.showwarning = _show_warning
        try:
            with _sigterm_as_interrupt():
                return _run(argv)
        except KeyboardInterrupt as interrupt:  # before a command started (building the parser, importing torch)
            word, status = _interrupted_status(interrupt)
            print(f"\ndisplex: {word}", file=sys.stderr)
            return status
        finally:
            if relaxed:
                stdout.reconfigure(errors="strict")


def _run(argv: list[str] | None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except _UsageError as err:
        print(f"displex: error: {one_line(str(err).removeprefix('displex ').removeprefix('displex: '))}", file=sys.stderr)
        return 2
    if not args.torch_threads:
        return _handle(args)  # without importing torch: `displex --help` stays quick
    from train.torch_threads import torch_threads

    with torch_threads(args.torch_threads):  # run() is also called in-process
        return _handle(args)


def _handle(args) -> int:
    """Run the parsed command; the exit status and its one-line messages are those of ``run``."""
    try:
        args.handler(args)
    except KeyboardInterrupt as interrupt:
        hint = getattr(args, "interrupted", None)
        hint = hint(args) if callable(hint) else hint
        word, status = _interrupted_status(interrupt)
        print(f"\ndisplex: {word}{'; ' + one_line(hint) if hint else ''}", file=sys.stderr)
        return status
    except InputError as err:
        print(f"displex: error: {one_line(err)}", file=sys.stderr)
        return 2
    except FileNotFoundError as err:
        print(f"displex: error: file not found: {one_line(err.filename)}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader of our output went away (``displex patterns list | head -1``): not an error
        # to report; stdout goes to devnull so that the interpreter's final flush stays quiet.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except OSError as err:
        name = os.fsdecode(err.filename) if err.filename is not None else None
        print(f"displex: error: {one_line(err.strerror or err)}{': ' + one_line(name) if name else ''}", file=sys.stderr)
        return 2
    except (MemoryError, RuntimeError) as err:
        # Python 3.11's Path.resolve reports a symbolic-link loop as a RuntimeError (3.13: OSError).
        if isinstance(err, RuntimeError) and str(err).startswith("Symlink loop"):
            print(f"displex: error: {one_line(err)}", file=sys.stderr)
            return 2
        # torch reports a failed CPU allocation as a RuntimeError; anything else is a bug.
        if not isinstance(err, MemoryError) and "can't allocate memory" not in str(err):
            raise
        print("displex: error: out of memory: the inputs (image size, pixel or pattern counts, panel resolution) need more memory than this machine has", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(run())
