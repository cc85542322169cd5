"""Comparison: config loading, the derived tables against plain computations, and a tiny end-to-end run."""
import dataclasses
import json
import math
import os
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from capture_sim.atomic import strict_json
from capture_sim.errors import DisplexWarning, InputError
from capture_sim.rig import load_rig
from capture_sim.synth import write_scene_set
from reconstruct.photometric_stereo import FLAG_NAMES
from patterns.families import make_patterns
from patterns.io import load_patterns
from train.compare import first_with_same_patterns, run_compare, run_demo
from train.compare_config import (
    DEFAULT_EXPOSURE_MS,
    CompareConfig,
    compare_config_from_dict,
    load_compare_config,
    repository_root,
    rig_exposure_ms,
)
from train.compare_methods import Method, collect_methods, external_methods
from train.report import _seconds, pivot_cell
from train.report_charts import CHARTS
from train.report_rows import aggregate_rows, summary_tables

SIZE = (24, 29)
REPO = repository_root(Path(__file__).resolve().parent.parent / "configs" / "compare" / "demo.toml")


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """The default scene set at 24 x 29 pixels, written as files (train/ and test/)."""
    folder = tmp_path_factory.mktemp("scenes")
    write_scene_set(folder, load_rig(), SIZE[0], SIZE[1], seed=0, progress=False)
    return folder


def tiny_config(scenes, **changes) -> CompareConfig:
    values = dict(
        pattern_counts=[2], noise_scales=[1.0], default_noise=1.0, heuristics=["tri_complementary"],
        learned={"steps": 2, "val_every": 0, "pixels_per_scene": 64},
        external=[{"name": "ddps_learned_M2", "path": "patterns/data/ddps/optimized_tri_random_2.npy"},
                  {"name": "ddps_learned_M4", "path": "patterns/data/ddps/optimized_tri_random_4.npy"}],
        train_scenes=[str(scenes / "train")], test_scenes=[str(scenes / "test")], scene_size=list(SIZE),
    )
    values.update(changes)
    return compare_config_from_dict(values, REPO)


def test_shipped_configs_load():
    for name in ("default", "demo"):
        config = load_compare_config(REPO / "configs" / "compare" / f"{name}.toml")
        assert len(config.noise_scales) >= 3 and config.default_noise in config.noise_scales
        assert config.search and config.external
        for item in config.external:
            assert (REPO / item.path).is_file()
    default = load_compare_config("default")
    assert default.seeds_for(4) == (0, 1, 2) and default.seeds_for(2) == (0,)
    assert default.search[0].num_patterns == 2
    demo = load_compare_config("demo")
    assert demo.train_config(10, 0).steps < demo.train_config(2, 0).steps
    for config in (default, demo):
        assert set(config.learned_pattern_counts()) == {2, 4, 10} and config.rerender_counts
        assert config.train_config(4, 0, rerender=True).rerender_weight > 0 == config.train_config(4, 0).rerender_weight


def test_config_out_is_relative_to_the_repository_root_like_its_other_paths(scenes):
    assert Path(tiny_config(scenes, out="runs/x").out) == REPO / "runs" / "x"
    assert tiny_config(scenes, out="/tmp/absolute").out == "/tmp/absolute"
    with pytest.raises(InputError, match="out"):
        tiny_config(scenes, out=" ")


def test_best_heuristic_is_never_a_method_that_reconstructed_nothing():
    from train.report_rows import learned_against_best

    rows = [{"kind": "learned", "M": 2, "mae": 30.0, "invalid_fraction": 0.5, "series": "learned", "label": "learned"},
            {"kind": "heuristic", "M": 2, "mae": 28.0, "invalid_fraction": 1.0, "series": "mono_gradient", "label": "mono_gradient"},
            {"kind": "heuristic", "M": 2, "mae": 33.0, "invalid_fraction": 0.6, "series": "tri_gradient", "label": "tri_gradient"}]
    (row,) = learned_against_best(rows, [2], 3000.0)
    assert row["best_heuristic"] == "tri_gradient" and row["ratio"] == pytest.approx(30 / 33)
    assert learned_against_best(rows[:2], [2], 3000.0) == []  # no heuristic reconstructed anything: no ratio


def test_resolved_config_keeps_non_finite_values_in_nested_tables(scenes):
    from train.compare_config import compare_config_to_dict

    config = tiny_config(scenes, learned={"steps": 2, "angle_cap_deg": float("inf")}, learned_at={"2": {"angle_cap_deg": float("inf")}},
                         solver={"restart_condition": float("inf")})
    written = json.loads(strict_json(compare_config_to_dict(config)))
    assert written["learned"]["angle_cap_deg"] == written["learned_at"]["2"]["angle_cap_deg"] == written["solver"]["restart_condition"] == "inf"


def test_config_errors(scenes):
    with pytest.raises(InputError, match="unknown key"):
        tiny_config(scenes, colour="red")
    with pytest.raises(InputError, match="default_noise"):
        tiny_config(scenes, default_noise=2.0)
    with pytest.raises(InputError, match="may not set"):
        tiny_config(scenes, learned={"num_patterns": 3})
    with pytest.raises(InputError, match="unknown key"):
        tiny_config(scenes, learned={"stepz": 3})
    with pytest.raises(InputError, match="families"):
        tiny_config(scenes, heuristics=["checkerboard"])
    with pytest.raises(InputError, match="algorithm"):
        tiny_config(scenes, search=[{"family": "tri_complementary", "M": 2, "algorithm": "simplex"}])
    with pytest.raises(InputError, match="not in pattern_counts"):
        tiny_config(scenes, rerender_counts=[4])
    with pytest.raises(InputError, match="not found"):
        tiny_config(scenes, external=[{"name": "gone", "path": "patterns/data/ddps/missing.npy"}])
    with pytest.raises(InputError, match="solver"):
        tiny_config(scenes, solver={"max_alternations": 0})
    with pytest.raises(InputError, match="eval_workers"):
        tiny_config(scenes, eval_workers=0)
    for table in ("learned_at", "learned_seeds_at"):  # named with the config, like every other error
        with pytest.raises(InputError, match=f"^compare config: {table} keys must be integers \\(M\\), got x"):
            tiny_config(scenes, **{table: {"x": {}}})
    with pytest.raises(InputError, match="learned: unknown key\\(s\\) stepz"):  # even with nothing learned
        tiny_config(scenes, learned={"stepz": 5}, learned_counts=[], rerender_counts=[])
    with pytest.raises(InputError, match="learned: steps"):  # a shared value that every M's table overrides
        tiny_config(scenes, learned={"steps": -1}, learned_at={"2": {"steps": 3}})
    with pytest.raises(InputError, match="pattern_counts must list at least one M"):
        tiny_config(scenes, pattern_counts=[], rerender_counts=[])
    with pytest.raises(InputError, match="rerender_counts M = 2 have no normal-only learning run"):
        tiny_config(scenes, learned_counts=[], rerender_counts=[2])
    with pytest.raises(InputError, match="learned: steps"):  # a wrong type even where nothing is learned
        tiny_config(scenes, learned={"steps": "5"}, learned_counts=[])
    with pytest.raises(InputError, match="external pattern names tri_complementary are also heuristic families"):
        tiny_config(scenes, external=[{"name": "tri_complementary", "path": "patterns/data/ddps/optimized_tri_random_2.npy"}])
    with pytest.raises(InputError, match="M and num_patterns are the same setting"):
        tiny_config(scenes, search=[{"family": "tri_complementary", "M": 2, "num_patterns": 4, "algorithm": "LN_SBPLX"}])


def test_an_output_folder_holding_the_source_package_is_refused(scenes, tmp_path):
    (tmp_path / "patterns").mkdir()
    (tmp_path / "patterns" / "__init__.py").write_text("")
    with pytest.raises(InputError, match="holds a Python package patterns/"):
        run_compare(tiny_config(scenes), tmp_path, progress=False)
    assert sorted(path.name for path in (tmp_path / "patterns").iterdir()) == ["__init__.py"]
    # A file where the output folder goes fails before the work, not when the results are written.
    (tmp_path / "afile").write_text("x")
    with pytest.raises(InputError, match="compare output folder .*valid UTF-8"):
        run_compare(tiny_config(scenes), tmp_path / os.fsdecode(b"out\xff"), progress=False)
    with pytest.raises(InputError, match="afile is a file, not a folder"):
        run_compare(tiny_config(scenes, learned_counts=[]), tmp_path / "afile", progress=False)


def test_relative_paths_resolve_against_the_repository_root(scenes):
    config = tiny_config(scenes)
    assert config.external[0].path == str(REPO / "patterns" / "data" / "ddps" / "optimized_tri_random_2.npy")
    assert config.train_scenes == (str(scenes / "train"),)


def test_published_initial_patterns_are_recognised_as_families():
    """The published initial tri_random files equal the family made here up to float rounding."""
    from patterns.families import make_patterns

    for count in (2, 4):
        published = np.load(REPO / "patterns" / "data" / "ddps" / f"initial_tri_random_{count}.npy")
        made = make_patterns("tri_random", count).numpy()
        other = make_patterns("tri_random", count, seed=1).numpy()
        methods = [Method(name, "heuristic", name, name, count, values) for name, values in
                   (("made", made), ("published", published), ("other", other), ("olat", "olat"), ("olat2", "olat"))]
        assert first_with_same_patterns(methods) == [0, 0, 2, 3, 3]


def test_capture_time_is_M_exposures_scaled_by_the_gain_over_all_white():
    from train.compare import SUMMARY_METRICS, summarise

    scenes = [{**{key: 1.0 for key in SUMMARY_METRICS}, "name": name, "exposure": gain, "flagged": {"dark": dark}}
              for name, gain, dark in (("a", 0.02, 0.5), ("b", 0.3, 0.0))]
    summary = summarise(scenes, 4, 440.0, [0.01, 0.1])
    assert summary["flagged"] == {"dark": 0.25}  # the scene mean of each flag's share
    # 4 images x 0.44 s x (2 and 3 times the all-white gain), averaged over the two scenes.
    assert summary["capture_seconds"] == pytest.approx(4 * 0.44 * (2 + 3) / 2)
    assert [scene["capture_seconds"] for scene in summary["scenes"]] == pytest.approx([4 * 0.44 * 2, 4 * 0.44 * 3])
    with pytest.raises(ValueError):
        summarise(scenes, 4, 440.0, [0.01])  # one white gain per scene


def test_olat_reference_and_olat_patterns_take_the_same_capture_time(scenes):
    """The OLAT reference's gain multiplies the raw OLAT stack, a pattern's the display's emission:
    lighting every superpixel once, either way, must cost about the same exposure time (the
    pattern version also carries the unlit superpixels' backlight, so it is a little brighter)."""
    from train.compare import summarise, white_exposures
    from train.evaluate import EvalSettings, evaluate_scene
    from train.search import prepare_scenes

    rig = dataclasses.replace(load_rig(), scale=7.0)  # the display's scale must cancel out
    test_scenes = prepare_scenes([scenes / "test"], "test", rig, SIZE, 0)[:2]
    whites = white_exposures(test_scenes, rig)
    olat_patterns = make_patterns("olat", rig.num_lights, rig.rows, rig.cols)
    reference = [evaluate_scene(pixels, "olat", EvalSettings(method="woodham", noise_scale=0.0), index).metrics for index, pixels in enumerate(test_scenes)]
    patterns = [evaluate_scene(pixels, olat_patterns, EvalSettings(noise_scale=0.0), index).metrics for index, pixels in enumerate(test_scenes)]
    reference_seconds = summarise(reference, rig.num_lights, 440.0, whites["olat"])["capture_seconds"]
    pattern_seconds = summarise(patterns, rig.num_lights, 440.0, whites["patterns"])["capture_seconds"]
    assert pattern_seconds <= reference_seconds <= 1.05 * pattern_seconds


def test_report_tables_escape_a_pipe_in_a_name():
    from train.report import _table

    table = _table(["method", "M"], [["mine|v2", "2"]]).splitlines()
    assert table[-1] == "| mine\\|v2 | 2 |" and all(line.replace("\\|", "").count("|") == 3 for line in table)


def test_noise_verdict_says_on_which_side_of_one_the_ratio_is():
    from train.report import noise_verdict

    assert noise_verdict(0.86, 0.80) == "the learned advantage grows"
    assert noise_verdict(0.86, 0.95) == "the learned advantage shrinks"
    assert noise_verdict(0.86, 0.865) == "the learned advantage stays about the same"
    assert noise_verdict(1.068, 1.0) == "learned patterns are no better than the best heuristic at either end"
    assert noise_verdict(0.95, 1.02) == "the learned advantage is lost"
    assert noise_verdict(1.02, 0.95) == "learned patterns overtake the best heuristic"


def test_rig_exposure_time():
    assert rig_exposure_ms(load_rig("dir-odyssey-ark"))[0] == 440.0
    assert rig_exposure_ms(load_rig("panel-32in-5x10"))[0] > 0
    assert rig_exposure_ms(load_rig("dir-odyssey-ark").with_resolution(10, 12))[0] == 440.0  # kept when resized
    untimed = dataclasses.replace(load_rig(), camera=dataclasses.replace(load_rig().camera, exposure_ms=None))
    exposure_ms, source = rig_exposure_ms(untimed)
    assert exposure_ms == DEFAULT_EXPOSURE_MS and source.startswith("default")


def test_unsupported_and_mismatched_methods_are_skipped_with_a_reason(scenes, tmp_path):
    config = tiny_config(scenes, pattern_counts=[1], heuristics=["tri_complementary", "olat"], learned_counts=[], include_olat_woodham=False)
    with pytest.warns(DisplexWarning, match=r"external pattern file .* skipped: its M = \d+ is not in pattern_counts \[1\]"):
        methods, skipped, _ = collect_methods(config, load_rig(), tmp_path, progress=False)
    assert [m.id for m in methods] == ["heuristic_olat_M1"]
    reasons = {s["method"]: s["reason"] for s in skipped}
    assert "supports M = 2..12" in reasons["tri_complementary"]
    assert reasons["ddps_learned_M2"] == reasons["ddps_learned_M4"] == "M is not in pattern_counts"



def test_a_heuristic_set_with_identical_patterns_is_skipped_with_the_reason(scenes, tmp_path, monkeypatch):
    # On a grid too small for a family, make_patterns refuses the set (its captures would repeat).
    def refuse(name, *args, **kwargs):
        raise InputError(f"{name}: M = 2 on a 1 x 6 grid gives identical patterns")

    monkeypatch.setattr("train.compare_methods.make_patterns", refuse)
    config = tiny_config(scenes, learned_counts=[], include_olat_woodham=False)
    methods, skipped, _ = collect_methods(config, load_rig(), tmp_path, progress=False)
    assert not [m for m in methods if m.kind == "heuristic"]
    assert {"method": "tri_complementary", "M": 2, "reason": "tri_complementary: M = 2 on a 1 x 6 grid gives identical patterns"} in skipped


def test_external_file_on_another_grid_is_skipped_with_a_warning(scenes, tmp_path):
    """One config serves rigs of several grids: a file that does not fit this rig is skipped, with
    the reason in the results and one warning line, not refused."""
    other_grid = tmp_path / "five_by_ten.npy"
    np.save(other_grid, np.full((2, 5, 10, 3), 0.5, dtype=np.float32))
    config, rig = tiny_config(scenes, external=[{"name": "small_panel", "path": str(other_grid)}]), load_rig()
    reason = f"patterns are 5 x 10, the rig is {rig.rows} x {rig.cols}"
    with pytest.warns(DisplexWarning, match=f"five_by_ten.npy skipped: {reason}"):
        methods, skipped = external_methods(config, rig)
    assert methods == [] and skipped == [{"method": "small_panel", "M": 2, "reason": reason}]


@pytest.mark.parametrize("changes, message", [
    (dict(search=[{"family": "grouped_olat", "M": 99, "algorithm": "LN_SBPLX"}], pattern_counts=[2, 99], learned_counts=[2]), "grouped_olat supports M = 1.."),
    (dict(search=[{"family": "tri_random", "M": 5, "algorithm": "LN_BOBYQA"}], pattern_counts=[2, 5], learned_counts=[2]), "2160 parameters"),
    (dict(search=[{"family": "tri_random", "M": 4, "algorithm": "LN_BOBYQA"}], pattern_counts=[2, 4], learned_counts=[2]), None),  # 1728: fine
    (dict(learned_at={2: {"init": "olat"}}, learned_counts=[4, 2], pattern_counts=[2, 4]), None),
    (dict(learned_at={1: {"init": "tri_complementary"}}, learned_counts=[2, 1], pattern_counts=[1, 2]), "tri_complementary supports M = 2.."),
    (dict(learned_counts=[2, 1], pattern_counts=[1, 2]), r"init 'auto' starts M = 1 .* set init to a family that does \(train's --init, or init in the config"),
])
def test_a_run_that_cannot_start_stops_the_comparison_before_learning(scenes, tmp_path, monkeypatch, changes, message):
    """Every learning start and search setup is checked before the first run: each used to fail
    only when its turn came, after the learning runs before it."""
    from train.compare_methods import _check_run_starts

    config = tiny_config(scenes, **changes)
    if message is None:
        _check_run_starts(config, load_rig())
        return

    def no_learning(*args, **kwargs):
        raise AssertionError("learning ran before every run's start was checked")

    monkeypatch.setattr("train.compare_methods.learned_method", no_learning)
    with pytest.raises(InputError, match=message):
        collect_methods(config, load_rig(), tmp_path / "patterns", progress=False)


def test_a_run_again_hides_its_earlier_run_in_its_own_log_folder(scenes, tmp_path):
    """A search or a fresh learning run that runs again (its earlier run interrupted, or its output
    deleted as a stale-run refusal says) hides that run's TensorBoard events in its own folder: they
    would overlap the new ones."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from train.compare_methods import learned_method, searched_method

    config = tiny_config(scenes, learned={"steps": 3, "val_every": 0, "pixels_per_scene": 32},
                         search=[{"family": "tri_complementary", "M": 2, "algorithm": "LN_SBPLX", "maxeval": 3, "pixels_per_scene": 32}])
    run, logdir, patterns = config.search[0], tmp_path / "tensorboard", tmp_path / "patterns"
    for _ in range(2):
        shutil.rmtree(patterns, ignore_errors=True)
        patterns.mkdir()
        searched_method(config, run, patterns, progress=False, logdir=logdir)
        learned_method(config, 2, 0, patterns, progress=False, logdir=logdir)
    for folder, tag, steps in ((run.name, "search/mae_deg", [0, 1, 2]), ("learned_M2_seed0", "train/loss", [1, 2, 3])):
        events = EventAccumulator(str(logdir / folder))
        events.Reload()
        assert [event.step for event in events.Scalars(tag)] == steps, folder


def test_unreadable_external_file_stops_the_comparison_before_learning(scenes, tmp_path, monkeypatch):
    bad = tmp_path / "bad.npy"
    np.save(bad, np.full((2, 9, 16, 3), 1.5))  # set values outside [0, 1]
    config = tiny_config(scenes, external=[{"name": "bad", "path": str(bad)}], learned_counts=[2])

    def no_learning(*args, **kwargs):
        raise AssertionError("learning ran before the external files were read")

    monkeypatch.setattr("train.compare_methods.learned_method", no_learning)
    with pytest.raises(InputError, match="bad.npy"):
        collect_methods(config, load_rig(), tmp_path / "patterns", progress=False)


def fake_results():
    """Results of three heuristics, two learned seeds and a search at M = 2, two noise levels."""
    def method(kind, series, mae_low, mae_high, seed=None, cost=None):
        evaluations = [{"noise_scale": noise, "mae": mae, "median": mae / 2, "under_10": 0.5, "invalid_fraction": 0.0, "exposure": 1.0,
                        "capture_seconds": 0.88, "simulate_reconstruct_seconds": 0.1, "reconstruct_seconds": 0.04} for noise, mae in ((0.5, mae_low), (2.0, mae_high))]
        return {"id": f"{series}{seed}", "kind": kind, "series": series, "label": series, "M": 2, "seed": seed, "cost_seconds": cost, "evaluations": evaluations}

    methods = [method("heuristic", "a", 10.0, 20.0), method("heuristic", "b", 12.0, 15.0), method("heuristic", "c", 30.0, 31.0),
               method("learned", "learned", 8.0, 17.0, seed=0, cost=10.0), method("learned", "learned", 9.0, 19.0, seed=1, cost=20.0),
               method("search", "s", 9.5, 14.0, cost=5.0)]
    return {"methods": methods, "noise_scales": [0.5, 2.0], "pattern_counts": [2], "default_noise": 0.5}


def test_summary_tables_against_plain_computation():
    results = fake_results()
    rows = {row["series"]: row for row in aggregate_rows(results, 2.0)}
    # Sample standard deviations over seeds: two seeds 2 degrees apart spread by sqrt(2).
    assert rows["learned"]["mae"] == pytest.approx(18.0) and rows["learned"]["mae_std"] == pytest.approx(math.sqrt(2.0))
    assert rows["a"]["mae_std"] == 0.0
    assert rows["learned"]["cost_seconds"] == pytest.approx(15.0) and rows["learned"]["seeds"] == 2
    # The label is the series' at every M; the seed count goes with each cell of the tables.
    assert rows["learned"]["label"] == "learned" and pivot_cell(rows["learned"], "mae", 2) == "18.00 (mean of 2 seeds)"
    assert pivot_cell(rows["a"], "mae", 2) == "20.00"
    assert pivot_cell(dict(rows["a"], invalid_fraction=1.0), "mae", 2) == "20.00 (all invalid)"
    assert pivot_cell(dict(rows["a"], invalid_fraction=1.0), "simulate_reconstruct_seconds", 1) == "0.1"
    assert pivot_cell(rows["a"], "reconstruct_seconds", None) == "0.040"  # a timing to two significant digits, not "0"
    assert [_seconds(value) for value in (0.2, 0.0934, 1.0, 9.96, 12.4, 250.0)] == ["0.20", "0.093", "1.0", "10", "12", "250"]
    assert pivot_cell(dict(rows["a"], invalid_fraction=0.9999), "mae", 2) == "20.00 (99.99% invalid)"  # nearly all: the placeholder
    assert pivot_cell(dict(rows["a"], invalid_fraction=0.98), "mae", 2) == "20.00"
    assert pivot_cell(dict(rows["a"], invalid_fraction=0.99996), "mae", 2) == "20.00 (99.99% invalid)"  # not rounded up to 100%
    assert pivot_cell(dict(rows["a"], invalid_fraction=0.9998999983), "mae", 2) == "20.00 (99.99% invalid)"  # 9999 of 10000, in floats
    assert pivot_cell(dict(rows["a"], invalid_fraction=0.99999996), "mae", 2) == "20.00 (99.99% invalid)"  # never 100%
    summary = summary_tables(results)
    by_noise = {c["noise_scale"]: c for c in summary["learned_vs_heuristic"]}
    assert by_noise[0.5]["best_heuristic"] == "a" and by_noise[0.5]["ratio"] == pytest.approx(8.5 / 10.0)
    assert by_noise[2.0]["best_heuristic"] == "b" and by_noise[2.0]["ratio"] == pytest.approx(18.0 / 15.0)
    assert by_noise[2.0]["best_tuned"] == "s" and by_noise[2.0]["ratio_tuned"] == pytest.approx(18.0 / 14.0)
    assert summary["rerender"] == []
    results["methods"].append(dict(results["methods"][3], id="rr", kind="rerender", series="learned_rerender", info={"rerender_weight": 0.5},
                                   evaluations=[dict(e, mae=mae) for e, mae in zip(results["methods"][3]["evaluations"], (6.0, 20.0))]))
    rerender = {r["noise_scale"]: r for r in summary_tables(results)["rerender"]}
    assert rerender[0.5]["normal_only_mae"] == 8.0 and rerender[0.5]["ratio"] == pytest.approx(6.0 / 8.0)
    assert rerender[2.0]["ratio"] == pytest.approx(20.0 / 17.0) and rerender[2.0]["weight"] == 0.5
    spread = {s["noise_scale"]: s for s in summary["seed_spread"]}
    assert spread[0.5]["seeds"] == [0, 1] and spread[0.5]["min"] == 8.0 and spread[0.5]["max"] == 9.0
    assert spread[2.0]["std"] == pytest.approx(np.std([17.0, 19.0], ddof=1))
    assert summary["specular_free"] == {"rows": [], "learned_vs_heuristic": []}


def test_learned_against_more_captures_against_plain_computation():
    results = fake_results()
    assert summary_tables(results)["learned_vs_more_captures"] == []  # one M only
    at_four = [dict(m, id=m["id"] + "_4", M=4, evaluations=[dict(e, mae=e["mae"] - 2.0) for e in m["evaluations"]]) for m in results["methods"]]
    results["methods"] += at_four
    results["pattern_counts"] = [2, 4]
    pairs = summary_tables(results)["learned_vs_more_captures"]
    # At the default noise 0.5: learned M = 2 averages 8.5; the best heuristic at M = 4 is a (10 - 2).
    assert [(c["M"], c["heuristic_M"], c["best_heuristic"]) for c in pairs] == [(2, 4, "a")]
    assert pairs[0]["learned_mae"] == pytest.approx(8.5) and pairs[0]["ratio"] == pytest.approx(8.5 / 8.0)
    for method in results["methods"]:  # all-invalid learned patterns at M = 2 match nothing
        if method["kind"] == "learned" and method["M"] == 2:
            for evaluation in method["evaluations"]:
                evaluation.update(invalid_fraction=1.0, mae=1.0)
    assert summary_tables(results)["learned_vs_more_captures"] == []


def test_specular_free_summary_against_plain_computation():
    results = fake_results()
    for method, mae in zip(results["methods"], (4.0, 3.0, 6.0, 3.5, 4.5, 5.0)):
        method["specular_free"] = dict(method["evaluations"][0], mae=mae, reconstruct_seconds=mae / 100)  # at the default noise (0.5)
    free = summary_tables(results)["specular_free"]
    rows = {row["series"]: row for row in free["rows"]}
    assert rows["learned"]["mae"] == pytest.approx(4.0) and rows["b"]["mae"] == 3.0
    # The times of the specular-free evaluations, not those of the main ones (0.04 s).
    assert rows["b"]["reconstruct_seconds"] == pytest.approx(0.03) and rows["learned"]["reconstruct_seconds"] == pytest.approx(0.04)
    (comparison,) = free["learned_vs_heuristic"]
    assert comparison["noise_scale"] == 0.5 and comparison["best_heuristic"] == "b" and comparison["ratio"] == pytest.approx(4.0 / 3.0)
    assert aggregate_rows(results, 2.0, specular_free=True) == []  # only measured at the default noise


def test_run_compare_end_to_end_and_resume(scenes, tmp_path, monkeypatch):
    config = tiny_config(scenes, rerender_counts=[2])
    results = run_compare(config, tmp_path, progress=False)
    for key in ("config", "rig", "exposure_ms", "methods", "skipped", "summary", "timings", "test_scenes", "noise_scales", "threads"):
        assert key in results
    assert json.loads((tmp_path / "results.json").read_text())["exposure_ms"] == 440.0
    kinds = {m["id"]: m["kind"] for m in results["methods"]}
    assert kinds == {"heuristic_tri_complementary_M2": "heuristic", "learned_M2_seed0": "learned", "learned_rerender_M2_seed0": "rerender",
                     "external_ddps_learned_M2": "external", "olat_woodham": "reference"}
    for method in results["methods"]:
        (evaluation,) = method["evaluations"]
        assert len(evaluation["scenes"]) == 4
        for key in ("mae", "median", "under_5", "under_30", "invalid_fraction", "exposure", "capture_seconds", "simulate_reconstruct_seconds", "reconstruct_seconds"):
            assert np.isfinite(evaluation[key])
        # The report's compute time is the reconstruction's, a part of simulation plus reconstruction.
        assert 0 < evaluation["reconstruct_seconds"] < evaluation["simulate_reconstruct_seconds"]
        assert set(evaluation["flagged"]) == set(FLAG_NAMES) and all(0 <= share <= 1 for share in evaluation["flagged"].values())
        assert [scene["name"] for scene in evaluation["scenes"]] == results["test_scenes"]
        # Exposure time scales with the gain relative to the all-white display, which no pattern outshines;
        # the reference's gain is in other units (test_olat_reference_and_olat_patterns_take_the_same_capture_time).
        whites = results["white_exposures_olat" if method["kind"] == "reference" else "white_exposures"]
        assert evaluation["capture_seconds"] == pytest.approx(np.mean([method["M"] * 0.44 * scene["exposure"] / white
                                                                       for scene, white in zip(evaluation["scenes"], whites)]))
        assert all(scene["exposure"] >= white * (1 - 1e-6) for scene, white in zip(evaluation["scenes"], whites))
    learned = next(m for m in results["methods"] if m["kind"] == "learned")
    assert learned["cost_seconds"] > 0 and (tmp_path / learned["pattern_file"]).is_file()
    assert results["skipped"] == [{"method": "ddps_learned_M4", "M": 4, "reason": "M is not in pattern_counts"}]
    assert results["summary"]["learned_vs_heuristic"][0]["best_heuristic"] == "tri_complementary"

    report = (tmp_path / "report.md").read_text()
    assert f"held-out test scenes of {SIZE[0]} x {SIZE[1]} pixels" in report  # the size the scenes have, not a setting
    assert results["summary"]["rerender"][0]["M"] == 2
    for text in ("method x M", "MAE against noise level", "How the advantage", "Capture time", "Compute time = wall seconds per scene of the reconstruction", "OLAT + Woodham", "normal + re-rendering",
                 "Heuristic families use preset default: off level 0, on level 1",
                 "Learning: M = 2: 2 steps from tri_complementary; training scenes: "):
        assert text in report
    for file_name in CHARTS.values():
        assert (tmp_path / file_name).stat().st_size > 0 and f"({file_name})" in report
    # The method x M compute-time table shows each row's median reconstruction time, as the per-M tables do.
    compute_table = report.split("Compute time (s per scene")[1].split("\n\n")[1]
    learned_row = next(row for row in aggregate_rows(results, 1.0) if row["kind"] == "learned")
    assert f"| {learned_row['label']} | learned | {_seconds(learned_row['reconstruct_seconds'])} |" in compute_table

    assert results["specular_free"] == {"enabled": True}
    for method in results["methods"]:
        free, (main,) = method["specular_free"], method["evaluations"]
        assert np.isfinite(free["mae"])
        # Same scenes and exposures; the matte cylinder has no specular stack, so it is measured exactly as before.
        assert [s["exposure"] for s in free["scenes"]] == [s["exposure"] for s in main["scenes"]]
        assert [s["name"] for s in free["scenes"]] == [s["name"] for s in main["scenes"]]
        matte = [s["name"] for s in main["scenes"]].index("test-08-cylinder-textured")
        assert free["scenes"][matte]["mae"] == main["scenes"][matte]["mae"]
    reference = next(m for m in results["methods"] if m["kind"] == "reference")
    # Woodham on the full OLAT stack fails on glossy pixels only: removing the specular stacks must help it.
    assert reference["specular_free"]["mae"] < reference["evaluations"][0]["mae"]
    assert "Where the error comes from" in report and "specular-free MAE" in report and "specular-free check" in report

    def no_learning(*args, **kwargs):
        raise AssertionError("a rerun must reuse the finished learning runs")

    monkeypatch.setattr("train.compare_methods.train_patterns", no_learning)
    again = run_compare(config, tmp_path, progress=False)
    assert next(m for m in again["methods"] if m["kind"] == "learned")["cost_seconds"] == pytest.approx(learned["cost_seconds"])
    # A rerun without the specular-free check neither keeps nor links the earlier run's chart.
    run_compare(dataclasses.replace(config, specular_free_check=False), tmp_path, progress=False)
    assert not (tmp_path / CHARTS["specular_free"]).exists() and CHARTS["specular_free"] not in (tmp_path / "report.md").read_text()
    # Scene files, or the rig's file (here a preset's), rewritten since the run (same paths, same
    # config) are not silently reused.
    from capture_sim.rig import rig_source

    for changed in (sorted((scenes / "train").glob("*.npz"))[0], rig_source(config.rig)):
        stat = changed.stat()
        os.utime(changed, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
        try:
            # Every stale run in one message, naming the changed file (the rig's: all of them).
            with pytest.raises(InputError, match=rf"made from input files .* rewritten, replaced or touched since \({changed.name}\)") as refused:
                run_compare(config, tmp_path, progress=False)
            if changed.suffix == ".toml":
                assert "earlier runs in" in str(refused.value) and str(refused.value).count(changed.name) >= 2, refused.value
        finally:
            os.utime(changed, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    # A rerun refused for another config leaves the last finished run's files as they were,
    # the heuristic pattern files included (they used to be rewritten before the refusal).
    before = {path: path.read_bytes() for path in (tmp_path / "patterns").glob("*.npz")}
    changed = tiny_config(scenes, learned={"steps": 3, "val_every": 0, "pixels_per_scene": 64}, heuristic_preset="ddps")
    with pytest.raises(InputError, match=r"another config \(settings that differ: steps\)"):
        run_compare(changed, tmp_path, progress=False)
    assert {path: path.read_bytes() for path in (tmp_path / "patterns").glob("*.npz")} == before
    # A rerun interrupted part-way (another heuristic preset and no specular-free check, stopped
    # in its evaluation or while its outputs are written) leaves the heuristic pattern files,
    # results, report and charts of the last finished run, which match.
    run_compare(config, tmp_path, progress=False)
    outputs = sorted((tmp_path / "patterns").glob("*.npz")) + sorted(tmp_path.glob("*.png")) + [tmp_path / name for name in ("results.json", "report.md", "config.json")]
    assert tmp_path / CHARTS["specular_free"] in outputs
    finished = {path: path.read_bytes() for path in outputs}

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    for stage in ("evaluate_methods", "write_json"):
        with monkeypatch.context() as patch:
            patch.setattr(f"train.compare.{stage}", interrupted)
            with pytest.raises(KeyboardInterrupt):
                run_compare(dataclasses.replace(config, heuristic_preset="ddps", specular_free_check=False), tmp_path, progress=False)
        assert {path: path.read_bytes() for path in outputs} == finished, stage
        assert not list(tmp_path.glob(".staging*"))
    # An external file in the patterns folder would be rewritten by the run that reads it.
    inside = tiny_config(scenes, external=[{"name": "mine", "path": str(tmp_path / "patterns" / "heuristic_tri_complementary_M2.npz")}])
    with pytest.raises(InputError, match=r"\[\[external\]\] mine: .* lies in .*patterns, whose files compare rewrites"):
        run_compare(inside, tmp_path, progress=False)
    assert {path: path.read_bytes() for path in (tmp_path / "patterns").glob("*.npz")} == before
    # So would a learning run's init pattern file there (it was overwritten: an input destroyed),
    # and a folder where a report file goes failed only after the work: both refused before it.
    init = tiny_config(scenes, learned={"steps": 2, "val_every": 0, "pixels_per_scene": 64,
                                        "init": str(tmp_path / "patterns" / "heuristic_tri_complementary_M2.npz")})
    with monkeypatch.context() as patch:
        patch.setattr("train.compare.collect_methods", lambda *args, **kwargs: pytest.fail("the work started"))
        with pytest.raises(InputError, match=r"learned init pattern file .* lies in .*patterns, whose files compare rewrites"):
            run_compare(init, tmp_path, progress=False)
        (tmp_path / "blocked" / "report.md").mkdir(parents=True)
        with pytest.raises(InputError, match="report.md: it exists and is not a regular file"):
            run_compare(config, tmp_path / "blocked", progress=False)
    assert {path: path.read_bytes() for path in (tmp_path / "patterns").glob("*.npz")} == before
    # A stop between a learning run's pattern file and its run record leaves a run to finish
    # again (from its checkpoint, to the same patterns), not a refusal blaming the rig file.
    learned_file = tmp_path / "patterns" / "learned_M2_seed0.npz"
    learned_values = load_patterns(learned_file)[0]
    learned_file.with_name("learned_M2_seed0.run.json").unlink()
    monkeypatch.undo()
    run_compare(config, tmp_path, progress=False)
    assert learned_file.with_name("learned_M2_seed0.run.json").is_file()
    assert np.array_equal(load_patterns(learned_file)[0], learned_values)
    # A pattern file deleted by hand leaves its record: the record goes before the run writes a
    # new file, so a stop between the two cannot pair the new file with the old record.
    learned_file.unlink()

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("train.compare_methods.train_patterns", stopped)
    with pytest.raises(KeyboardInterrupt):
        run_compare(config, tmp_path, progress=False)
    assert not learned_file.with_name("learned_M2_seed0.run.json").exists()


def test_test_scenes_listed_twice_are_refused_and_training_scenes_among_them_warned(scenes, tmp_path):
    from train.compare import _check_scene_lists

    twice = tiny_config(scenes, test_scenes=[str(scenes / "test"), str(scenes / "test") + "/"])
    with pytest.raises(InputError, match="test_scenes name the same scene file twice"):
        run_compare(twice, tmp_path, progress=False)
    leaking = tiny_config(scenes, test_scenes=[str(scenes / "train")])
    with pytest.warns(DisplexWarning, match=r"test scene\(s\) are also training scenes"):
        shared = _check_scene_lists(leaking)
    assert shared == sorted(path.name for path in (scenes / "train").glob("*.npz"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _check_scene_lists(dataclasses.replace(leaking, learned_counts=[], search=())) == []  # nothing learned there: no warning
        assert _check_scene_lists(tiny_config(scenes)) == []
    # The report says which test scenes are not held out.
    from train.report import _measurement_caption

    results = {"test_scenes": ["a", "b"], "test_pixels": 5, "rig": "r", "grid": [2, 3], "methods": [], "default_noise": 1.0,
               "exposure_ms": 440.0, "exposure_ms_source": "rig", "config": {}, "test_files_also_trained": ["a.npz"]}
    assert _measurement_caption(results).startswith("Measured on 2 test scenes (1 of them also used for learning or searches, so not held out: a.npz)")
    assert _measurement_caption(dict(results, test_files_also_trained=[])).startswith("Measured on 2 held-out test scenes")


def test_demo_reuses_only_a_scene_set_of_its_own_settings(tmp_path):
    from capture_sim.synth import write_scene_set
    from train.compare import _scene_set_matches

    config = dataclasses.replace(load_compare_config("demo"), scene_size=[8, 10])
    rig = load_rig(config.rig)
    write_scene_set(tmp_path / "plain", rig, 8, 10, config.scene_seed, progress=False)
    write_scene_set(tmp_path / "shadows", rig, 8, 10, config.scene_seed, cast_shadows=True, progress=False)
    assert _scene_set_matches(tmp_path / "plain" / "index.json", rig, config)
    assert not _scene_set_matches(tmp_path / "shadows" / "index.json", rig, config)
    assert not _scene_set_matches(tmp_path / "plain" / "index.json", rig, dataclasses.replace(config, scene_seed=config.scene_seed + 1))
    # A listed scene file deleted, or another one added beside them: the set is not reused.
    test_files = sorted((tmp_path / "plain" / "test").glob("*.npz"))
    extra = tmp_path / "plain" / "train" / "extra.npz"
    extra.write_bytes(test_files[0].read_bytes())
    assert not _scene_set_matches(tmp_path / "plain" / "index.json", rig, config)
    extra.unlink()
    # A hidden .npz (an interrupted atomic write's temporary file) is not a scene added: the set
    # is still reused (it was synthesised again on every run).
    (tmp_path / "plain" / "test" / ".a.npz.9b8qxr63.npz").write_bytes(b"half a zip")
    assert _scene_set_matches(tmp_path / "plain" / "index.json", rig, config)
    test_files[-1].unlink()
    assert not _scene_set_matches(tmp_path / "plain" / "index.json", rig, config)


def test_demo_runs_on_a_tiny_config(tmp_path, capsys, monkeypatch):
    config_path = tmp_path / "configs" / "compare" / "tiny.toml"
    config_path.parent.mkdir(parents=True)
    config_path.write_text(
        "pattern_counts = [2]\nnoise_scales = [0.5, 1.0]\nheuristics = ['tri_gradient']\nscene_size = [20, 24]\n"
        "include_olat_woodham = false\n[learned_at.2]\nsteps = 50\n[learned]\nval_every = 0\npixels_per_scene = 64\n"
        "[[search]]\nfamily = 'tri_complementary'\nM = 2\nmaxeval = 2\npixels_per_scene = 50\n"
    )
    results = run_demo(tmp_path / "demo", progress=False, config_path=config_path, steps=1)
    assert (tmp_path / "demo" / "scenes" / "index.json").is_file()
    assert results["config"]["train_scenes"] == [str((tmp_path / "demo" / "scenes" / "train").resolve())]
    learned = next(m for m in results["methods"] if m["kind"] == "learned")
    assert learned["info"]["steps"] == 1
    assert {m["kind"] for m in results["methods"]} == {"heuristic", "learned", "search"}
    assert "report.md" in capsys.readouterr().out
    # The same folder named relative to another working directory: the runs are reused.
    monkeypatch.chdir(tmp_path / "configs")
    again = run_demo(Path("..") / "demo", progress=False, config_path=config_path, steps=1)
    assert next(m for m in again["methods"] if m["kind"] == "learned")["cost_seconds"] == pytest.approx(learned["cost_seconds"])


def test_parallel_subset_evaluation_matches_in_process_and_deduplicates(scenes, tmp_path):
    """Workers and duplicate pattern sets change nothing; a pixel subset is fixed per scene."""
    from train.compare import evaluate_methods, evaluation_columns
    from train.search import prepare_scenes

    rig = load_rig()
    test_scenes = prepare_scenes([scenes / "test"], "test", rig, SIZE, 0)
    config = tiny_config(scenes, eval_pixels_per_scene=40, solver={"max_shadow_iterations": 4})
    columns = evaluation_columns(test_scenes, 40, 0)
    assert all(c is not None and c.numel() == 40 and (c.diff() > 0).all() for c in columns)
    assert all(torch.equal(a, b) for a, b in zip(columns, evaluation_columns(test_scenes, 40, 0)))

    def methods():
        patterns = np.load(REPO / "patterns" / "data" / "ddps" / "initial_tri_complementary.npy").astype(np.float32)
        # "b" is "a" up to float rounding (one unit in the last place), as a published file of a family.
        rounded = np.nextafter(patterns, np.float32(0.5))
        return [Method("a", "heuristic", "a", "a", 2, patterns), Method("b", "external", "b", "b", 2, rounded),
                Method("olat_woodham", "reference", "olat_woodham", "OLAT", rig.num_lights, "olat")]

    serial, parallel = methods(), methods()
    whites = {"patterns": [0.01] * len(test_scenes), "olat": [0.01] * len(test_scenes)}
    evaluate_methods(serial, test_scenes, config, 440.0, whites, progress=False)
    # More workers than jobs: the extra ones are never started (2^62 of them used to loop for ever).
    evaluate_methods(parallel, test_scenes, dataclasses.replace(config, eval_workers=2**62), 440.0, whites, progress=False)
    assert serial[1].info["same_patterns_as"] == "a" and serial[1].evaluations[0]["mae"] == serial[0].evaluations[0]["mae"]
    for one, other in zip(serial, parallel):
        for first, second in zip(one.evaluations, other.evaluations):
            assert [s["mae"] for s in first["scenes"]] == [s["mae"] for s in second["scenes"]]
    assert serial[2].evaluations[0]["mae"] < serial[0].evaluations[0]["mae"]


def test_ctrl_c_during_parallel_evaluation_stops_the_workers(scenes, monkeypatch, python_sigint):
    """Ctrl-C reaches the workers and the parent (one process group). Emulated without signalling
    the group (that would reach the test runner): each job interrupts its own worker, one also
    the parent, and both sleep. The workers must ignore it and the parent must stop them and raise
    KeyboardInterrupt at once; it used to hang on a worker that died holding a pool's queue lock."""
    import multiprocessing
    import os
    import signal
    import time

    import train.compare as compare
    from train.search import prepare_scenes

    methods = [Method(name, "heuristic", name, name, 2, make_patterns(name, 2).numpy()) for name in ("tri_complementary", "tri_gradient")]

    def interrupted_job(patterns, *args):
        os.kill(os.getpid(), signal.SIGINT)  # ignored by a worker
        if np.array_equal(patterns, methods[0].patterns):  # one Ctrl-C for the parent
            time.sleep(0.5)  # the parent is waiting for results by now
            os.kill(os.getppid(), signal.SIGINT)
        time.sleep(60)

    monkeypatch.setattr(compare, "_evaluate_job", interrupted_job)  # forked workers inherit it
    config = tiny_config(scenes, eval_workers=2)
    test_scenes = prepare_scenes([scenes / "test"], "test", load_rig(), SIZE, 0)
    began = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        compare.measure_methods(methods, test_scenes, config, (1.0,), progress=False)
    assert time.perf_counter() - began < 30 and not multiprocessing.active_children()


WORKERS_OF_A_KILLED_PARENT = """
import os, sys, time
import numpy as np
import train.compare as compare
from capture_sim.rig import load_rig
from patterns.families import make_patterns
from train.compare_methods import Method
from train.search import prepare_scenes
from tests.test_compare import SIZE, tiny_config

scenes, pids = sys.argv[1], sys.argv[2]
def slow_job(*args):
    with open(os.path.join(pids, str(os.getpid())), "w"):
        pass
    time.sleep(120)
compare._evaluate_job = slow_job  # the forked workers inherit it
methods = [Method(name, "heuristic", name, name, 2, make_patterns(name, 2).numpy()) for name in ("tri_complementary", "tri_gradient")]
test_scenes = prepare_scenes([os.path.join(scenes, "test")], "test", load_rig(), SIZE, 0)
compare.measure_methods(methods, test_scenes, tiny_config(__import__("pathlib").Path(scenes), eval_workers=2), (1.0,), progress=False)
"""


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc (Linux)")
def test_evaluation_workers_end_with_a_parent_killed_without_clean_up(scenes, tmp_path):
    """SIGKILL (or the OOM killer) gives the parent no chance to stop its workers: they used to
    finish every job for nobody (70 s on a 2-core machine after the parent died)."""
    import signal
    import subprocess
    import sys
    import time

    pids = tmp_path / "pids"
    pids.mkdir()
    parent = subprocess.Popen([sys.executable, "-c", WORKERS_OF_A_KILLED_PARENT, str(scenes), str(pids)], cwd=Path(__file__).parent.parent)
    try:
        deadline = time.monotonic() + 120
        while len(list(pids.iterdir())) < 2 and parent.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        workers = [int(path.name) for path in pids.iterdir()]
        assert len(workers) == 2, parent.poll()
    finally:
        parent.send_signal(signal.SIGKILL)
        parent.wait()

    def alive(pid):
        try:
            return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
        except (FileNotFoundError, IndexError):
            return False

    deadline = time.monotonic() + 10
    while any(map(alive, workers)) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = [pid for pid in workers if alive(pid)]
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    assert not left


def test_a_worker_whose_parent_is_gone_runs_no_more_jobs(monkeypatch):
    """Where the kernel cannot end a worker with its parent (no prctl: macOS), the worker checks
    before each job and stops."""
    import train.compare as compare

    run, sent = [], []

    class Connection:
        def send(self, message):
            sent.append(message)

        def close(self):
            sent.append("closed")

    monkeypatch.setattr(compare, "_init_worker", lambda parent: None)
    monkeypatch.setattr(compare, "_evaluate_keyed", lambda job: run.append(job) or (job, []))
    compare._worker_main(["a", "b"], Connection(), os.getppid())
    assert run == ["a", "b"] and sent == [("result", ("a", [])), ("result", ("b", [])), "closed"]
    run.clear(), sent.clear()
    compare._worker_main(["a", "b"], Connection(), -1)  # not this process's parent
    assert run == [] and sent == ["closed"]


def test_an_error_in_a_parallel_evaluation_job_reaches_the_caller(scenes, monkeypatch):
    import multiprocessing

    import train.compare as compare
    from train.search import prepare_scenes

    def failing_job(*args):
        raise InputError("scene x: something is wrong")

    monkeypatch.setattr(compare, "_evaluate_job", failing_job)
    methods = [Method(name, "heuristic", name, name, 2, make_patterns(name, 2).numpy()) for name in ("tri_complementary", "tri_gradient")]
    test_scenes = prepare_scenes([scenes / "test"], "test", load_rig(), SIZE, 0)
    with pytest.raises(InputError, match="scene x: something is wrong"):
        compare.measure_methods(methods, test_scenes, tiny_config(scenes, eval_workers=2), (1.0, 4.0), progress=False)
    assert not multiprocessing.active_children()


def test_specular_free_evaluation_is_the_evaluation_of_the_diffuse_scenes(scenes, tmp_path):
    """``evaluate_specular_free`` measures each method on ``Scene.without_specular`` copies, at the
    default noise, with the comparison's pixels, noise draws and the main evaluation's exposures; a
    scene without a usable diffuse stack skips the check with its reason."""
    from capture_sim.scene import load_scene, scene_paths
    from train.compare import evaluate_methods, evaluate_specular_free, evaluation_columns, specular_free_scenes
    from train.evaluate import EvalSettings, evaluate_scene
    from train.search import prepare_scenes

    rig = load_rig()
    raw = [load_scene(path) for path in scene_paths([scenes / "test"])]
    free_scenes, reason = specular_free_scenes(raw, rig)
    assert reason is None and len(free_scenes) == len(raw)
    assert np.array_equal(raw[0].without_specular().olat, raw[0].diffuse) and raw[0].without_specular().specular is None
    config = tiny_config(scenes, eval_pixels_per_scene=40, solver={"max_shadow_iterations": 4})
    patterns = np.load(REPO / "patterns" / "data" / "ddps" / "initial_tri_complementary.npy").astype(np.float32)
    methods = [Method("a", "heuristic", "a", "a", 2, patterns)]
    whites = {"patterns": [0.01] * len(free_scenes), "olat": [0.01] * len(free_scenes)}
    evaluate_methods(methods, prepare_scenes([scenes / "test"], "test", rig, SIZE, 0), config, 440.0, whites, progress=False)
    evaluate_specular_free(methods, free_scenes, config, 440.0, whites, progress=False)
    # The main evaluation's pixels (its scenes' masks) and exposures, set here independently.
    main_scenes = prepare_scenes([scenes / "test"], "test", rig, SIZE, 0)
    columns = evaluation_columns(main_scenes, 40, config.eval_seed)
    direct = []
    for index, (pixels, subset) in enumerate(zip(free_scenes, columns)):
        gain = methods[0].evaluations[0]["scenes"][index]["exposure"]
        settings = EvalSettings(noise_scale=config.default_noise, seed=config.eval_seed, ps=config.ps_config(), exposure=gain)
        direct.append(evaluate_scene(pixels, torch.as_tensor(patterns), settings, index, subset).metrics["mae"])
    assert [scene["mae"] for scene in methods[0].specular_free["scenes"]] == direct

    missing = dataclasses.replace(raw[1], diffuse=None)
    assert specular_free_scenes([raw[0], missing], rig) == (None, f"{missing.label} has no separate diffuse stack")
    assert "file" in missing.meta and missing.meta["file"] in missing.label  # the file the user can find, not only the meta name
    metal = dataclasses.replace(raw[1], diffuse=np.zeros_like(raw[1].diffuse))
    assert "zero inside the mask" in specular_free_scenes([metal], rig)[1]
    assert raw[0].without_specular().olat.dtype == raw[0].olat.dtype
    with pytest.raises(InputError, match="diffuse must be float16 or float32, got float64"):  # as olat, refused with the scene
        dataclasses.replace(raw[0], diffuse=raw[0].diffuse.astype(np.float64))


def test_specular_free_section_states_a_skipped_or_disabled_check():
    from train.report import specular_free_section

    results = fake_results()
    summary = summary_tables(results)
    assert specular_free_section(dict(results, specular_free={"enabled": False}), summary, summary["rows"]) == []
    lines = specular_free_section(dict(results, specular_free={"enabled": True, "skipped": "scene x has no separate diffuse stack"}), summary, summary["rows"])
    assert "Skipped: scene x has no separate diffuse stack." in lines
    # The share is '-' exactly where the tables say "(all invalid)" both ways, not already at 99%.
    for method in results["methods"]:
        method["specular_free"] = dict(method["evaluations"][0], mae=method["evaluations"][0]["mae"] / 2)
    for invalid, share in ((0.995, "50"), (1.0, "-")):
        for method in results["methods"]:
            for evaluation in (*method["evaluations"], method["specular_free"]):
                evaluation["invalid_fraction"] = invalid
        summary = summary_tables(results)
        lines = specular_free_section(dict(results, specular_free={"enabled": True}), summary, summary["rows"])
        table = "\n".join(lines).splitlines()
        assert any(line.startswith("| a | 2 |") and line.rstrip(" |").endswith(f" {share}") for line in table), table


def test_rig_file_in_a_compare_config_is_relative_to_the_repository(tmp_path):
    from train.compare_config import compare_config_from_dict

    config = compare_config_from_dict({"rig": "rigs/mine.toml", "scene_size": [8, 10]}, root=tmp_path)
    assert config.rig == str(tmp_path / "rigs" / "mine.toml")
    assert compare_config_from_dict({"rig": "dir-odyssey-ark"}, root=tmp_path).rig == "dir-odyssey-ark"


def test_relative_learned_init_file_resolves_against_the_repository(scenes):
    """A [learned] init pattern file is found like an [[external]] one, from any working folder."""
    config = tiny_config(scenes, learned={"steps": 2, "init": "patterns/data/ddps/initial_tri_random_2.npy"},
                         learned_at={2: {"init": "tri_gradient"}})
    assert Path(config.learned["init"]) == REPO / "patterns" / "data" / "ddps" / "initial_tri_random_2.npy"
    assert config.learned_at[2]["init"] == "tri_gradient"  # a family name stays a name
    assert config.train_config(2, 0).rerender_weight == 0.0 and config.train_config(2, 0, rerender=True).rerender_weight > 0


def test_cost_chart_labels_its_axis_when_every_cost_is_below_a_second():
    """A log axis inside one decade has no major tick: its minor ticks carry the numbers."""
    from train.report_charts import chart_mae_vs_cost

    rows = aggregate_rows(fake_results(), 0.5)
    for row, seconds in zip(rows, (0.15, 0.23, 0.4, 0.6, 0.86)):
        row["simulate_reconstruct_seconds"] = seconds
    fig = chart_mae_vs_cost(rows, "simulate_reconstruct_seconds", "compute (s)", "speed", "caption")
    fig.canvas.draw()
    ax = fig.axes[0]
    labels = [t.get_text() for t in (*ax.xaxis.get_majorticklabels(), *ax.xaxis.get_minorticklabels()) if t.get_text()]
    low, high = ax.get_xlim()
    shown = [float(text) for text in labels if low <= float(text) <= high]
    assert {0.2, 0.5} <= set(shown) and not {0.3, 0.4, 0.6} & set(shown), labels
    assert ax.get_xlabel() == "compute (s); log scale"  # log axes say so


def test_cost_chart_over_several_decades_labels_its_major_ticks_only():
    """On an axis over more than MINOR_LABEL_DECADES the minor labels ran together ("500", "1000",
    "2000" on the capture-time chart); the merged legend's long failure explanation comes last."""
    from train.report_charts import FAILED_LABEL, _legend_entries, chart_mae_vs_cost

    rows = aggregate_rows(fake_results(), 0.5)
    for row, seconds in zip(rows, (1.2, 3.0, 50.0, 400.0, 2000.0)):
        row["simulate_reconstruct_seconds"] = seconds
    rows.append(dict(rows[0], series="dead", label="dead", kind="external", mae=60.0, invalid_fraction=1.0))
    fig = chart_mae_vs_cost(rows, "simulate_reconstruct_seconds", "compute (s)", "speed", "caption")
    fig.canvas.draw()
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.xaxis.get_minorticklabels() if t.get_text()] == []
    low, high = ax.get_xlim()
    assert {float(t.get_text()) for t in ax.xaxis.get_majorticklabels() if t.get_text() and low <= float(t.get_text()) <= high} == {1, 10, 100, 1000}
    assert list(_legend_entries([ax]))[-1] == FAILED_LABEL


def test_cost_chart_draws_failed_methods_in_a_band_and_merges_coincident_labels():
    """Methods with (nearly) every pixel invalid are drawn crossed out, with their own markers side
    by side, in a band above the data (not at the placeholder's MAE, where real results may sit);
    methods on one point share one "M=" label."""
    from train.report_charts import FAILED_BAND, FAILED_LABEL, chart_mae_vs_cost

    rows = aggregate_rows(fake_results(), 0.5)
    rows.append(dict(next(row for row in rows if row["series"] == "s"), series="s2", label="s2"))  # the search's twin
    rows.append(dict(rows[0], series="dead", label="dead", kind="external", mae=60.0, invalid_fraction=1.0))
    rows.append(dict(rows[0], series="nearly", label="nearly", kind="external", mae=60.0, invalid_fraction=0.9999))
    fig = chart_mae_vs_cost(rows, "simulate_reconstruct_seconds", "compute (s)", "speed", "caption")
    ax = fig.axes[0]
    in_band = [line for line in ax.get_lines() if list(line.get_ydata()) == [FAILED_BAND]]
    crosses = [line for line in in_band if line.get_marker() == "x"]
    assert len(crosses) == 2 and [line.get_label() for line in crosses].count(FAILED_LABEL) == 1
    styles = {(line.get_marker(), line.get_color()) for line in in_band if line.get_marker() != "x"}
    assert len(styles) == 2 and {marker for marker, _ in styles} == {"s"}  # the two external sets' own styles
    positions = {tuple(line.get_transform().transform((0.1, FAILED_BAND))) for line in crosses}
    assert len(positions) == 2  # side by side, not on top of each other
    assert 60.0 not in [y for line in ax.get_lines() if line not in in_band for y in line.get_ydata()]
    assert ax.get_ylim()[1] < 60.0  # the placeholder's MAE does not stretch the axis
    annotations = [child.get_text() for child in ax.texts]
    # learned and the two searches sit at 0.1 s; the search twins coincide; failed methods get no label.
    assert sorted(annotations) == ["M=2", "M=2"], annotations
    assert FAILED_LABEL in [text.get_text() for text in ax.get_legend().get_texts()]
    # The x axis reaches a failed method's cost, as it would a real point's (placed by x alone).
    rows[-1] = dict(rows[-1], simulate_reconstruct_seconds=1000.0)
    ax = chart_mae_vs_cost(rows, "simulate_reconstruct_seconds", "compute (s)", "speed", "caption").axes[0]
    assert ax.get_xlim()[1] >= 1000.0


def test_count_labels_move_aside_instead_of_covering_each_other():
    """Two labelled points a few pixels apart (not close enough to share a label) get labels at
    different offsets, so neither covers the other."""
    from train.report_charts import _label_counts
    from train.figures import plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.set_xscale("log")
    ax.plot([0.5, 0.52, 3.0], [11.0, 11.1, 20.0], linestyle="none", marker="o")
    ax.set_xlim(0.1, 10.0)
    ax.set_ylim(0.0, 30.0)
    _label_counts(ax, [(0.5, 11.0, 4), (0.52, 11.1, 144), (3.0, 20.0, 2)])
    offsets = {text.get_text(): tuple(text.xyann) for text in ax.texts}
    assert set(offsets) == {"M=4", "M=144", "M=2"}
    assert offsets["M=4"] != offsets["M=144"] and offsets["M=2"] == (4, 3)
    plt.close(fig)


def test_mae_chart_close_up_spans_the_best_methods_and_leaves_out_all_invalid_ones():
    """The close-up panel runs from just below the lowest MAE to 1.4 x the worst per-M best, with
    the OLAT reference line when near; an all-invalid row (MAE of the placeholder) does not stretch it."""
    from train.report_charts import chart_mae_vs_patterns, close_up_limits

    def row(kind, count, mae, invalid=0.0):
        return {"kind": kind, "series": f"{kind}{count}{mae}", "label": kind, "M": count, "mae": mae, "mae_std": 0.0, "invalid_fraction": invalid}

    rows = [row("learned", 2, 10.0), row("learned", 4, 8.0), row("heuristic", 2, 30.0), row("heuristic", 4, 40.0, invalid=1.0)]
    assert close_up_limits(rows) == pytest.approx((0.95 * 8.0, 1.4 * 10.0))
    assert close_up_limits(rows + [row("reference", 144, 16.0)]) == pytest.approx((0.95 * 8.0, 1.05 * 16.0))
    assert close_up_limits(rows + [row("reference", 144, 50.0)]) == pytest.approx((0.95 * 8.0, 1.4 * 10.0))  # too far: left out
    assert close_up_limits([row("heuristic", 2, 40.0, invalid=1.0)]) is None
    fig = chart_mae_vs_patterns(rows, "caption")
    assert fig.axes[1].get_ylim() == pytest.approx((0.95 * 8.0, 1.4 * 10.0))
    from train.report_charts import FAILED_LABEL

    # The failure band is on the full panel; the one legend (beside the close-up) explains it.
    assert FAILED_LABEL in [text.get_text() for text in fig.axes[1].get_legend().get_texts()]


def test_families_section_says_what_each_family_is_and_where_every_pixel_was_invalid():
    from train.report import families_section

    def method(series, count, invalid, flagged=None):
        evaluation = {"noise_scale": 1.0, "mae": 40.0, "invalid_fraction": invalid, **({"flagged": flagged} if flagged else {})}
        return {"kind": "heuristic", "series": series, "M": count, "evaluations": [evaluation]}

    results = {"default_noise": 1.0, "methods": [
        method("mono_gradient", 2, 1.0, {"ill_conditioned": 1.0, "back_facing": 0.4, "grazing": 0.0}), method("mono_gradient", 4, 0.1),
        method("tri_complementary", 2, 0.05), method("gray_noise", 4, 1.0), method("mono_random", 4, 0.5)]}  # gray_noise: a record without flags
    text = "\n".join(families_section(results))
    assert "- mono_gradient: grey linear ramps" in text and "Every pixel invalid at M = 2 (flagged ill_conditioned: too few or too similar captures)." in text
    assert "- tri_complementary: R/G/B halves" in text and text.count("Every pixel invalid") == 2
    assert "- gray_noise: 0.5 grey" in text and "Every pixel invalid at M = 4." in text
    assert "Many pixels invalid: 50% at M = 4, counted in the MAE at the placeholder normal." in text and text.count("Many pixels") == 1
    assert "three independent lighting directions" in text
    assert families_section({"default_noise": 1.0, "methods": [method("mono_gradient", 4, 0.1)]})[-2].startswith("- mono_gradient")  # no failure: no explanation
    assert families_section({"default_noise": 1.0, "methods": []}) == []


def test_report_text_follows_the_config_that_ran():
    """No sentence about learning, searches, the OLAT reference, heuristic presets or BOBYQA where
    the comparison had none; seeds 'at every M' only where learning ran at every M."""
    from train.report import _capture_text, _measurement_caption, _preset_text, _search_section, _timing_text, _trained_noise_text, summary_section

    results = fake_results()
    results.update(test_scenes=["x"], test_pixels=10, rig="r", grid=[2, 3], exposure_ms=440.0, exposure_ms_source="rig",
                   config={"heuristic_preset": "default"})
    for method in results["methods"]:
        method["info"] = {"steps": 2, "init": "tri_complementary"}
    assert _trained_noise_text(results) == " Learning and searches used noise scale 0.5."
    assert "OLAT reference" not in _measurement_caption(results) and "OLAT reference" not in _capture_text(results, False)
    assert "preset default" in _preset_text(results)
    only_heuristics = dict(results, methods=[m for m in results["methods"] if m["kind"] == "heuristic"])
    assert _trained_noise_text(only_heuristics) == "" and "used noise scale" not in _measurement_caption(only_heuristics)
    assert _preset_text(dict(results, methods=[m for m in results["methods"] if m["kind"] != "heuristic"])) == ""
    assert _trained_noise_text(dict(results, methods=[m for m in results["methods"] if m["kind"] == "search"])) == " Searches used noise scale 0.5."
    searched = dict(results["methods"][-1], series="search:tri_complementary:LN_SBPLX", M=2,
                    info={"trace_png": "t.png", "evaluations": 3, "start_mae": 1.0, "best_mae": 0.5, "stop_reason": "maxeval"})
    assert "2 P + 1" not in "\n".join(_search_section(dict(results, methods=[searched]), Path(".")))
    bobyqa = dict(searched, series="search:tri_complementary:LN_BOBYQA")
    assert "2 P + 1" in "\n".join(_search_section(dict(results, methods=[bobyqa]), Path(".")))
    wider = dict(results, pattern_counts=[2, 4])  # learning (and every method) ran at M = 2 only
    text = "\n".join(summary_section(wider, summary_tables(wider)))
    assert "2 learning seeds at M = 2" in text and "every M" not in text and "- M = 4: no method ran at this M." in text
    # Seed counts that differ per M read as counts, not as seed values.
    uneven = dict(wider, methods=[*wider["methods"], dict(wider["methods"][3], id="l4", M=4)])
    text = "\n".join(summary_section(uneven, summary_tables(uneven)))
    assert "from 2 learning seeds at M = 2, 1 learning seed at M = 4" in text
    assert _timing_text(dict(results, threads=1)) == ", on 1 thread" and _timing_text(dict(results, threads=2)) == ", on 2 threads"


def test_external_and_searched_sets_never_share_a_style_in_one_chart():
    """Styles used to come from a hash of the name: 'trigrad_copy' and 'ddps_M4' were both brown squares."""
    from matplotlib.colors import to_hex

    from train.report_charts import chart_mae_vs_cost

    rows = aggregate_rows(fake_results(), 0.5)
    template = next(row for row in rows if row["series"] == "a")
    names = ["trigrad_copy", "ddps_M4", "e3", "e4", "e5"]
    assert sum(map(ord, names[0])) % 4 == sum(map(ord, names[1])) % 4  # the old collision
    rows += [dict(template, kind="external", series=f"external:{name}", label=name) for name in names]
    fig = chart_mae_vs_cost(rows, "simulate_reconstruct_seconds", "compute (s)", "speed", "caption")
    styles = {line.get_label(): (to_hex(line.get_color()), line.get_marker()) for line in fig.axes[0].get_lines() if line.get_label() in names}
    assert len(styles) == len(names) and len(set(styles.values())) == len(names), styles


def test_report_names_externals_the_reference_flags_and_the_training_noise():
    from train.report import _noise_section, _reference_flags, externals_section

    results = fake_results()
    results["methods"].append({"id": "ext", "kind": "external", "series": "external:pub", "label": "pub", "M": 2, "pattern_file": "p/pub.npy",
                               "seed": None, "cost_seconds": None, "evaluations": results["methods"][0]["evaluations"]})
    assert "- pub (M = 2): p/pub.npy" in externals_section(results)
    assert externals_section(dict(results, methods=results["methods"][:3])) == []
    reference = {"id": "ref", "kind": "reference", "series": "reference", "label": "OLAT", "M": 144, "seed": None, "cost_seconds": None,
                 "evaluations": [dict(results["methods"][0]["evaluations"][0], flagged={"poor_fit": 0.404, "saturated": 0.076, "dark": 0.0})]}
    results["methods"].append(reference)
    assert _reference_flags(results) == " (a poor fit on 40.4% of the pixels)"
    reference["evaluations"][0]["flagged"]["poor_fit"] = 0.996
    assert _reference_flags(results) == " (a poor fit on 99.6% of the pixels)"
    text = _noise_section(results, aggregate_rows(results, 0.5))[2]
    assert "learning and searches used noise scale 0.5 only" in text
    assert "used noise scale" not in _noise_section(dict(results, methods=results["methods"][:3]), aggregate_rows(results, 0.5))[2]
    assert "used noise scale" not in _noise_section(dict(results, noise_scales=[0.5]), aggregate_rows(results, 0.5))[2]  # one level only


def test_cost_chart_heuristic_markers_grow_with_M():
    """Heuristic points carry no M label (they would pile up): their size says M, the caption says so."""
    from train.report_charts import HEURISTIC_MARKER_SIZES, chart_mae_vs_cost

    rows = aggregate_rows(fake_results(), 0.5)
    rows.append(dict(next(row for row in rows if row["series"] == "a"), M=4, mae=8.0))
    fig = chart_mae_vs_cost(rows, "simulate_reconstruct_seconds", "compute (s)", "speed", "caption.")
    heuristic_a = [line for line in fig.axes[0].get_lines() if len(line.get_ydata()) == 1 and line.get_ydata()[0] in (10.0, 8.0)]
    assert sorted(line.get_markersize() for line in heuristic_a) == list(HEURISTIC_MARKER_SIZES[:2])
    assert sum(1 for line in fig.axes[0].get_lines() if line.get_label() == "a") == 1  # one legend entry per family
    assert "marker size grows with M (2, 4)" in fig.texts[-1].get_text()


def test_summary_states_the_answer_first_against_plain_computation():
    """Per M, the most accurate method and the learned / best-heuristic ratio with the test scenes
    the learned patterns win (mean over seeds per scene); the evidence behind them."""
    from train.report import summary_section

    results = fake_results()
    per_scene = {"a": (9.0, 11.0), "learned0": (8.0, 12.0), "learned1": (10.0, 8.0)}  # learned mean (9, 10) against a's (9, 11)
    for method in results["methods"]:
        for evaluation in method["evaluations"]:
            maes = per_scene.get(method["id"], (evaluation["mae"], evaluation["mae"]))
            evaluation["scenes"] = [{"name": f"scene{i}", "mae": mae} for i, mae in enumerate(maes)]
    results["test_scenes"] = ["scene0", "scene1"]
    summary = summary_tables(results)
    text = "\n".join(summary_section(results, summary))
    assert "- M = 2: lowest mean error: learned patterns, MAE 8.50 deg" in text  # (8 + 9) / 2 at noise 0.5 beats search 9.5 and a 10
    assert "; best heuristic family a 10.00 deg; learned / heuristic 0.850, learned better on 1 of 2 test scenes" in text
    assert "2 test scenes" in text and "from 2 learning seeds at every M" in text and "placeholder normal" in text
    assert "lowest median" not in text  # learned has the lowest median too (4.25 against the search's 4.75)
    heuristic_a = next(m for m in results["methods"] if m["id"] == "aNone")
    heuristic_a["evaluations"][0].update(median=3.0, invalid_fraction=0.02)
    text = "\n".join(summary_section(results, summary_tables(results)))
    assert "; lowest median: a, 3.00 deg against 4.25 (invalid pixels 2.0% against 0.0%" in text
    heuristic_a["evaluations"][0].update(invalid_fraction=0.0)  # no more invalid pixels: no such explanation
    text = "\n".join(summary_section(results, summary_tables(results)))
    assert "; lowest median: a, 3.00 deg against 4.25;" in text and "(invalid pixels" not in text
    heuristic_a["evaluations"][0].update(median=4.24)  # within TIE_MARGIN of the winner's 4.25: no clause
    assert "lowest median" not in "\n".join(summary_section(results, summary_tables(results)))
    comparisons = {c["noise_scale"]: c for c in summary["learned_vs_heuristic"]}
    assert comparisons[0.5]["best_tuned"] == "s"
    no_search = fake_results()
    no_search["methods"] = [m for m in no_search["methods"] if m["kind"] != "search"]
    assert all(c["best_tuned"] is None and c["ratio_tuned"] is None for c in summary_tables(no_search)["learned_vs_heuristic"])
    # All-invalid learned patterns win nothing; an M where every method is all-invalid is said so;
    # without learned runs nothing is said of learning seeds.
    for method in results["methods"]:
        if method["kind"] == "learned":
            for evaluation in method["evaluations"]:
                evaluation.update(invalid_fraction=1.0, mae=1.0)
    text = "\n".join(summary_section(results, summary_tables(results)))
    assert "the learned patterns leave every pixel invalid" in text and "better on" not in text and "lowest mean error: learned" not in text
    # ... and no re-rendering ratio against them (the placeholder MAE is no baseline).
    learned_seed0 = next(m for m in results["methods"] if m["id"] == "learned0")
    results["methods"].append(dict(learned_seed0, id="rr", kind="rerender", series="learned_rerender", info={"rerender_weight": 0.5},
                                   evaluations=[dict(e, mae=5.0, invalid_fraction=0.1) for e in learned_seed0["evaluations"]]))
    assert summary_tables(results)["rerender"] == []
    results["methods"].pop()
    for method in results["methods"]:
        for evaluation in method["evaluations"]:
            evaluation["invalid_fraction"] = 1.0
    assert "- M = 2: every method leaves every pixel invalid" in "\n".join(summary_section(results, summary_tables(results)))
    results["methods"] = [m for m in results["methods"] if m["kind"] != "learned"]
    assert "seed" not in "\n".join(summary_section(results, summary_tables(results)))


def test_all_invalid_learned_patterns_get_no_ratio_anywhere_in_the_report():
    """The placeholder normal's MAE is no measurement: an all-invalid learned set is marked in the
    advantage table, named in the noise verdict, and left out of the specular sentence."""
    from train.report import _advantage_section, specular_free_section

    results = fake_results()
    for method in results["methods"]:
        if method["kind"] == "learned":
            method["evaluations"][1].update(invalid_fraction=1.0, mae=14.0)  # every pixel invalid at noise 2 only
        method["specular_free"] = dict(method["evaluations"][0])
    summary = summary_tables(results)
    text = "\n".join(_advantage_section(summary, results["pattern_counts"]))
    assert "14.00 (all invalid)" in text and "ratio 0.850 (noise 0.5) -> every pixel invalid (noise 2)" in text
    assert "the learned patterns leave every pixel invalid at noise 2" in text and "as the noise rises" not in text
    for method in results["methods"]:
        if method["kind"] == "learned":
            method["evaluations"][0].update(invalid_fraction=1.0)
            method["specular_free"].update(invalid_fraction=1.0)
    summary = summary_tables(results)
    lines = specular_free_section(dict(results, specular_free={"enabled": True}), summary, summary["rows"])
    assert "- M = 2: the learned patterns leave every pixel invalid (no ratio)." in lines, lines


def test_per_scene_table_against_plain_computation():
    """Each cell is that scene's MAE: the learned seeds' mean, the best heuristic family's (best
    over all scenes, not per scene) and the OLAT reference's, in test-scene order."""
    from train.report import scene_section

    results = fake_results()
    results["test_scenes"] = ["sphere", "capsule"]
    per_scene = {"a": (9.0, 11.0), "b": (20.0, 4.0), "c": (30.0, 30.0), "learned": None, "s": (9.0, 10.0)}
    for method in results["methods"]:
        for evaluation in method["evaluations"]:
            maes = per_scene[method["series"]] or ((5.0, 7.0) if method["seed"] == 0 else (6.0, 10.0))
            evaluation["scenes"] = [{"name": name, "mae": mae} for name, mae in zip(results["test_scenes"], maes)]
    results["methods"].append({"id": "olat", "kind": "reference", "series": "olat", "label": "OLAT + Woodham", "M": 144, "seed": None,
                               "cost_seconds": None, "evaluations": [dict(results["methods"][0]["evaluations"][0], scenes=[
                                   {"name": "sphere", "mae": 1.0}, {"name": "capsule", "mae": 2.5}])]})
    lines = scene_section(results, summary_tables(results))
    table = [row for line in lines for row in line.splitlines() if row.startswith("|")]
    # At noise 0.5 family a (scene mean 10.0) beats b (12.0), although b wins on the capsule.
    assert table[0] == "| scene | learned, M = 2 | a, M = 2 | OLAT + Woodham |"
    assert table[2:] == ["| sphere | 5.50 | 9.00 | 1.00 |", "| capsule | 8.50 | 11.00 | 2.50 |"]
    # Two files may carry one scene name: rows go by position. An all-invalid scene is marked.
    results["test_scenes"] = ["same", "same"]
    results["methods"][0]["evaluations"][0]["scenes"][1]["invalid_fraction"] = 1.0
    table = [row for line in scene_section(results, summary_tables(results)) for row in line.splitlines() if row.startswith("|")]
    assert table[2:] == ["| same | 5.50 | 9.00 | 1.00 |", "| same | 8.50 | 11.00 (all invalid) | 2.50 |"]


def test_report_reader_fixes():
    """From a reader's review: a specular-free ratio within TIE_MARGIN of 1 is called even, not a
    loss; the noise table marks all-invalid cells; an external set that is a heuristic's copy is
    said to be one measurement; compute time is the median over every evaluation of a method."""
    from train.report import _accuracy_section, _noise_section, specular_free_section

    results = fake_results()
    for method in results["methods"]:
        method["specular_free"] = dict(method["evaluations"][0])
        method["evaluations"][1]["reconstruct_seconds"] = 0.5 if method["series"] == "a" else 0.04
    for method in results["methods"]:
        if method["kind"] == "learned":
            method["specular_free"]["mae"] = 10.05  # against a's 10.0: ratio 1.005
    summary = summary_tables(results)
    text = "\n".join(specular_free_section(dict(results, specular_free={"enabled": True}), summary, summary["rows"]))
    assert "without it the two are even" in text and "is better" not in text
    results["methods"][0]["evaluations"][0].update(invalid_fraction=1.0)
    rows = aggregate_rows(results, 0.5)
    assert "| a | 2 | 10.00 (all invalid) | 20.00 |" in "\n".join(_noise_section(results, rows))
    by_series = {row["series"]: row for row in rows}
    assert by_series["a"]["reconstruct_seconds"] == pytest.approx(np.median([0.04, 0.5]))  # test scenes only, every noise
    # Verdicts call a ratio within TIE_MARGIN of 1 even; timings keep two significant digits.
    from train.report import _seconds, _timing_text, noise_verdict

    assert noise_verdict(0.995, 1.005) == "learned patterns are no better than the best heuristic at either end"
    assert noise_verdict(0.995, 0.9) == "learned patterns overtake the best heuristic"
    assert [_seconds(v) for v in (0.0044, 0.009, 0.15, 1.234, None)] == ["0.0044", "0.0090", "0.15", "1.2", "-"]
    from train.report import _fmt

    assert [_fmt(-0.29, 0), _fmt(-0.004), _fmt(-0.6, 0), _fmt(None)] == ["0", "0.00", "-1", "-"]  # no '-0' in a table
    assert _timing_text({"config": {"eval_workers": 2}, "threads": 2}) == (
        ", single-threaded in up to 2 worker processes sharing the machine (on 2 threads when one set is evaluated)")
    results["methods"][2]["info"] = {"same_patterns_as": results["methods"][1]["id"]}
    text = "\n".join(_accuracy_section(results, rows))
    assert "Evaluated once, so their rows repeat the other's numbers: c holds the same patterns as b at M = 2." in text


def test_search_trace_links_resolve_from_the_report(tmp_path, monkeypatch):
    """A trace chart recorded relative to the output folder links as is; one recorded by an older
    version relative to the working directory links relative to the report too."""
    from train.report import _search_section

    out_dir = tmp_path / "runs" / "x"
    (out_dir / "patterns").mkdir(parents=True)
    (out_dir / "patterns" / "s.trace.png").write_bytes(b"png")
    monkeypatch.chdir(tmp_path)
    for recorded in ("patterns/s.trace.png", "runs/x/patterns/s.trace.png", str(out_dir / "patterns" / "s.trace.png")):
        method = {"kind": "search", "label": "s + LN_BOBYQA", "M": 2, "cost_seconds": 1.0, "evaluations": [{"noise_scale": 1.0, "mae": 9.0}],
                  "info": {"evaluations": 3, "start_mae": 10.0, "best_mae": 9.5, "stop_reason": "maxeval reached", "trace_png": recorded}}
        text = "\n".join(_search_section({"methods": [method], "default_noise": 1.0}, out_dir))
        assert "[trace](patterns/s.trace.png)" in text, recorded


def test_a_stale_run_names_the_comparison_settings_that_differ(scenes, monkeypatch):
    """The run's own field names (val_scenes, noise_scale) are not the ones the user edited."""
    import train.compare_methods as compare_methods
    from train.config_io import config_to_dict

    config = tiny_config(scenes)
    run = config.train_config(2, 0)
    recorded = dict(config_to_dict(run), val_scenes=["elsewhere"], noise_scale=4.0, steps=99)
    monkeypatch.setattr(compare_methods, "load_patterns", lambda path: (None, {"config": recorded}))
    reason = compare_methods._stale_reason(Path("x.npz"), run)
    assert reason == "made with another config (settings that differ: default_noise, steps, test_scenes (the learning runs' validation))"


def test_missing_compare_configs_and_odd_scene_paths_are_named_plainly(tmp_path):
    """A missing config path is not reported as PATH.toml; a bad preset name lists the presets; a
    scene path that exists but is no file or folder is not 'not found'."""
    from capture_sim.scene import scene_paths

    with pytest.raises(InputError, match=r"compare config not found: .*missing$"):
        load_compare_config(tmp_path / "missing")
    with pytest.raises(InputError, match=r"no compare config demoo \(a TOML file, or a preset: default, demo\)"):
        load_compare_config("demoo")
    assert Path(load_compare_config("demo").out).name == "demo"
    with pytest.raises(InputError, match=r"compare config not found: \./mine$"):
        load_compare_config("./mine")
    (tmp_path / "demo").mkdir()  # e.g. the demo's output folder, where the command runs
    cwd = os.getcwd()
    try:
        os.chdir(tmp_path)
        assert Path(load_compare_config("demo").out).name == "demo"  # still the preset
    finally:
        os.chdir(cwd)
    os.symlink(tmp_path / "gone.npz", tmp_path / "link.npz")
    with pytest.raises(InputError, match="is a link to .*gone.npz, which is not found"):
        scene_paths([tmp_path / "link.npz"])
    os.mkfifo(tmp_path / "fifo")
    with pytest.raises(InputError, match="is not a file or folder"):
        scene_paths([tmp_path / "fifo"])
    with pytest.raises(InputError, match="scene path not found"):
        scene_paths([tmp_path / "gone.npz"])
    # A hidden .npz is an interrupted atomic write's temporary file (or macOS's ._name.npz), not a scene.
    folder = tmp_path / "set"
    folder.mkdir()
    (folder / "a.npz").write_bytes(b"")
    (folder / ".a.npz.9b8qxr63.npz").write_bytes(b"half a zip")
    assert scene_paths([folder]) == [folder / "a.npz"]
    (folder / "a.npz").unlink()
    with pytest.raises(InputError, match="no scene .npz files in folder"):
        scene_paths([folder])


def test_report_text_names_only_what_the_comparison_ran_and_tells_twin_scenes_apart():
    """A comparison without learning or searches still defined "Cost" by them and explained the
    learned / other ratios; scenes of two sets with the same names (other seeds) had rows nobody
    could tell apart."""
    from train.report import _cost_text, scene_labels

    results = fake_results()
    assert _cost_text(results) == (" Cost = wall seconds of a learning run (its steps see the training scenes only; the time includes "
                                   "loading the held-out scenes and validating on them) or of a search.")
    heuristics_only = dict(results, methods=[method for method in results["methods"] if method["kind"] == "heuristic"])
    assert _cost_text(heuristics_only) == ""
    searched = dict(results, methods=[method for method in results["methods"] if method["kind"] != "learned"])
    assert _cost_text(searched) == " Cost = wall seconds of a search."
    twins = {"test_scenes": ["bowl", "cup", "bowl", "cup", "disc"],
             "test_scene_files": ["/a/s0/bowl.npz", "/a/s0/cup.npz", "/a/s1/bowl2.npz", "/a/s1/cup.npz", "/a/disc.npz"]}
    assert scene_labels(twins) == ["bowl (bowl.npz)", "cup (/a/s0/cup.npz)", "bowl (bowl2.npz)", "cup (/a/s1/cup.npz)", "disc"]
    assert scene_labels({"test_scenes": ["bowl", "bowl"]}) == ["bowl", "bowl"]  # results written before the files were recorded
