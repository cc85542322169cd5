"""NLopt search: the generic minimiser on closed-form objectives, and `run_search` on tiny scenes."""
import csv
import dataclasses
import json
import time
import warnings

import nlopt
import numpy as np
import pytest
import torch

from capture_sim.errors import InputError
from capture_sim.rig import load_rig
from capture_sim.scene import save_scene
from capture_sim.synth import synthesize_scene
from patterns.families import default_vector, get_family
from patterns.io import load_patterns
from train.scene_pixels import scene_pixels
import train.search
from train.search import (ALGORITHMS, MAX_QUADRATIC_PARAMETERS, PatternObjective, SearchConfig, minimise, output_files,
                          partial_trace_path, prepare_scenes, run_search, trace_csv)

SIZE = (24, 29)
TARGET = np.array([0.3, -0.2, 0.6])
LOW, HIGH = -np.ones(3), np.ones(3)


def quadratic(x, need_gradient):
    """f(x) = |x - TARGET|^2, minimum 0 at TARGET, gradient 2 (x - TARGET)."""
    difference = x - TARGET
    return float(difference @ difference), (2 * difference if need_gradient else None)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    """Two tiny training scenes with true normals, written as scene files."""
    rig = load_rig()
    folder = tmp_path_factory.mktemp("scenes")
    for index, (shape, material) in enumerate((("sphere", "lambertian"), ("blob", "svbrdf"))):
        save_scene(synthesize_scene(shape, material, rig, SIZE[0], SIZE[1], seed=index), folder / f"{shape}.npz")
    return folder


def test_search_config_refuses_a_sharpness_the_families_refuse():
    from patterns.families import MAX_SHARPNESS

    with pytest.raises(InputError, match="sharpness must be positive and at most"):
        SearchConfig(sharpness=MAX_SHARPNESS * 10)


@pytest.mark.parametrize("algorithm", ["LN_BOBYQA", "LN_SBPLX", "LD_MMA", "LD_LBFGS", "GN_CRS2_LM"])
def test_minimise_improves_and_keeps_history(algorithm):
    start = np.array([-0.5, 0.5, 0.0])
    calls = []
    found = minimise(quadratic, start, LOW, HIGH, algorithm, maxeval=40, seed=1, on_evaluation=lambda *args: calls.append(args))
    values = [value for _, value in found.history]
    assert 1 <= len(found.history) <= 40 and len(calls) == len(found.history)
    assert found.start_value == pytest.approx(quadratic(start, False)[0])
    assert found.best_value == min(values) <= found.start_value
    assert found.best_value == pytest.approx(quadratic(found.best_x, False)[0])
    assert [best for *_, best in calls] == list(np.minimum.accumulate(values))
    if algorithm != "GN_CRS2_LM":  # a global population method gets no closer in 40 evaluations
        assert found.best_value < 1e-2 * found.start_value


def test_minimise_respects_maxeval_and_single_evaluation():
    found = minimise(quadratic, np.zeros(3), LOW, HIGH, "GN_ESCH", maxeval=7, seed=0)
    assert len(found.history) == 7
    only = minimise(quadratic, np.zeros(3), LOW, HIGH, "LN_BOBYQA", maxeval=1)
    assert len(only.history) == 1 and np.array_equal(only.best_x, np.zeros(3))


@pytest.mark.parametrize("algorithm", ["LN_BOBYQA", "LN_COBYLA", "GN_CRS2_LM", "GN_DIRECT_L", "LD_MMA"])
def test_roundoff_exception_returns_best_point(algorithm):
    evaluations = []

    def fragile(x, need_gradient):
        if len(evaluations) == 4:
            raise nlopt.RoundoffLimited("simulated round-off")
        evaluations.append(x.copy())
        return quadratic(x, need_gradient)

    found = minimise(fragile, np.array([0.9, 0.9, 0.9]), LOW, HIGH, algorithm, maxeval=30)
    assert len(found.history) == 4
    assert "RoundoffLimited" in found.stop_reason
    values = [quadratic(x, False)[0] for x in evaluations]
    assert found.best_value == pytest.approx(min(values))
    assert np.allclose(found.best_x, evaluations[int(np.argmin(values))])


def test_an_nlopt_failure_returns_the_best_point():
    """A gradient that disagrees with the value makes LD_LBFGS's line search fail (nlopt 2.11 raises
    nlopt.runtime_error, no longer a RuntimeError): the search still ends with the best point seen."""
    def misleading(x, need_gradient):
        value, gradient = quadratic(x, need_gradient)
        return value, (None if gradient is None else -gradient)

    found = minimise(misleading, np.zeros(3), LOW, HIGH, "LD_LBFGS", maxeval=50)
    assert found.stop_reason.startswith("stopped:") and 1 < len(found.history) < 50
    assert found.best_value == min(value for _, value in found.history)


def test_points_asked_again_cost_no_evaluation():
    """Algorithms that return to a point (LN_SBPLX to its start) are answered from memory: the
    trace has one row per distinct evaluation."""
    found = minimise(quadratic, np.zeros(3), LOW, HIGH, "LN_SBPLX", maxeval=40)
    points = [x.tobytes() for x, _ in found.history]
    assert len(points) == len(set(points)) > 10  # with one remembered point, the start came twice
    # Nor do they spend the budget: NLopt's own count includes them (SBPLX made 28 of 30), and
    # -0.0 is the same point as 0.0 (BOBYQA asked for its start again with a zero's sign flipped).
    for algorithm, maxeval in (("LN_SBPLX", 30), ("LN_BOBYQA", 2)):
        found = minimise(bumpy, np.array([0.0, -0.0, 0.5]), -np.ones(3), np.ones(3), algorithm, maxeval, xtol_rel=0, ftol_abs=0)
        points = {x.tobytes() for x, _ in found.history}
        assert len(found.history) == len(points) == maxeval and found.stop_reason == "maxeval reached", (algorithm, found.stop_reason)


def bumpy(x, need_gradient):
    """A quadratic with ripples: local algorithms keep searching near its minimum."""
    return float(((x - 0.3) ** 2).sum() + 0.01 * np.sin(10 * x).sum()), 2 * (x - 0.3) + 0.1 * np.cos(10 * x)


def test_maxtime_stops_the_search():
    def slow(x, need_gradient):
        time.sleep(0.02)
        return quadratic(x, need_gradient)

    found = minimise(slow, np.zeros(3), LOW, HIGH, "GN_DIRECT_L", maxeval=10_000, maxtime=0.2)
    assert found.stop_reason == "maxtime reached"
    assert 1 <= len(found.history) < 10_000  # timing-based: a stalled machine may manage only the start


def test_other_objective_errors_propagate():
    def broken(x, need_gradient):
        if x[0] != 0.5:
            raise ZeroDivisionError("bug")
        return quadratic(x, need_gradient)

    with pytest.raises(ZeroDivisionError):
        minimise(broken, np.array([0.5, 0.0, 0.0]), LOW, HIGH, "GN_CRS2_LM", maxeval=10)


def test_bad_inputs_raise():
    with pytest.raises(InputError, match="LN_BOBYQA"):
        SearchConfig(algorithm="LN_NELDERMEAD")
    with pytest.raises(InputError, match="families"):
        SearchConfig(family="checkerboard")
    with pytest.raises(InputError):
        SearchConfig(maxeval=0)
    with pytest.raises(InputError):
        SearchConfig(maxtime=-1.0)
    with pytest.raises(InputError, match="xtol_rel"):
        SearchConfig(xtol_rel=-1.0)
    with pytest.raises(InputError, match="algorithms"):
        minimise(quadratic, np.zeros(3), LOW, HIGH, "nelder-mead", maxeval=3)
    with pytest.raises(InputError, match="outside"):
        minimise(quadratic, np.full(3, 2.0), LOW, HIGH, "LN_BOBYQA", maxeval=3)
    with pytest.raises(InputError, match="finite"):
        minimise(quadratic, np.zeros(3), LOW, np.full(3, np.inf), "GN_DIRECT_L", maxeval=3)


def test_trace_csv_columns_and_running_best():
    history = [(np.array([1.0, 2.0]), 5.0), (np.array([1.5, 2.0]), 7.0), (np.array([0.5, 2.0]), 3.0)]
    rows = list(csv.reader(trace_csv(["a", "b"], history).splitlines()))
    assert rows[0] == ["index", "a", "b", "mae", "best_so_far"]
    assert [float(row[-1]) for row in rows[1:]] == [5.0, 5.0, 3.0]


def test_trace_chart_marks_where_bobyqa_probes_end():
    from train.search import trace_figure

    history = [(np.zeros(2), value) for value in (5.0, 6.0, 4.0, 4.5, 4.4, 3.0, 2.5)]
    fig = trace_figure(history, "title", "caption", probes=5)  # P = 2: 2 P + 1 = 5 probes
    lines = {line.get_label(): line for line in fig.axes[0].get_lines()}
    assert list(lines["first steps after 5 probes"].get_xdata()) == [4.5, 4.5]
    assert "first steps after 5 probes" not in {line.get_label() for line in trace_figure(history, "t", "c").axes[0].get_lines()}
    # Stopped among the probes: no line, and the title says that the drop was no progress.
    among = trace_figure(history[:3], "t", "c", probes=5).axes[0]
    assert len(among.get_lines()) == 2 and "all 3 evaluations were probes around the start" in among.get_title()
    assert "probes" not in fig.axes[0].get_title()
    assert lines["best so far"].get_drawstyle() == "steps-post"  # a best so far holds until the next evaluation


def test_objective_gradient_matches_central_differences():
    # The objective jumps slightly wherever a pixel's attached-shadow mask flips (the implicit
    # gradient holds the masks fixed), so only parameters with a smooth effect are compared, at a
    # moderate step, on a noise-free scene large enough to average the jumps out.
    rig = load_rig()
    scenes = [scene_pixels(synthesize_scene("blob", "svbrdf", rig, 48, 58, seed=1), rig, require_normals=True)]
    objective = PatternObjective("tri_gradient", 2, scenes, rig.rows, rig.cols, noise_scale=0.0, pixels_per_scene=0)
    names = [p.name for p in get_family("tri_gradient").parameters(2)]
    x = default_vector("tri_gradient", 2, lo=0.15, hi=0.8).numpy()
    value, gradient = objective(x, True)
    # solve_ps's differentiable path moves its float32 output by ~1e-3 deg.
    assert value == pytest.approx(objective(x, False)[0], abs=1e-2)
    assert np.isfinite(gradient).all()
    for name in ("hi", "pair0_g_radius"):
        index = names.index(name)
        step = np.zeros_like(x)
        step[index] = 0.03
        central = (objective(x + step, False)[0] - objective(x - step, False)[0]) / 0.06
        assert gradient[index] == pytest.approx(central, rel=0.35), name


@pytest.mark.parametrize("algorithm", ["LN_BOBYQA", "LD_MMA"])
def test_run_search_writes_patterns_trace_and_chart(scene_dir, tmp_path, algorithm):
    config = SearchConfig(family="tri_complementary", num_patterns=2, algorithm=algorithm, maxeval=5, scenes=(str(scene_dir),), scene_size=SIZE, pixels_per_scene=200)
    out = tmp_path / "best.npz"
    summary = run_search(config, out, logdir=tmp_path / "logs", progress=False)
    assert summary["best_mae"] <= summary["start_mae"]
    assert 1 <= summary["evaluations"] <= 5 and summary["seconds"] > 0

    rows = list(csv.DictReader((tmp_path / "best.trace.csv").read_text().splitlines()))
    assert len(rows) == summary["evaluations"]
    assert [int(row["index"]) for row in rows] == list(range(len(rows)))
    bests = [float(row["best_so_far"]) for row in rows]
    assert bests == list(np.minimum.accumulate([float(row["mae"]) for row in rows]))
    assert bests[-1] == pytest.approx(summary["best_mae"])
    assert (tmp_path / "best.trace.png").stat().st_size > 0
    assert json.loads((tmp_path / "best.config.json").read_text())["algorithm"] == algorithm
    assert any((tmp_path / "logs").iterdir())

    patterns, meta = load_patterns(out)
    assert patterns.shape == (2, 9, 16, 3)
    assert meta["made_by"] == "displex search" and meta["algorithm"] == algorithm and meta["family"] == "tri_complementary"
    assert list(meta["parameters"]) == meta["parameter_names"] == list(rows[0])[1:-2]
    # The file holds the patterns exactly as evaluated: re-evaluating them gives the recorded MAE.
    rig = load_rig()
    objective = PatternObjective("tri_complementary", 2, prepare_scenes([scene_dir], "train", rig, SIZE, 0), rig.rows, rig.cols, pixels_per_scene=200)
    with torch.no_grad():
        assert float(objective.value(torch.as_tensor(patterns))) == pytest.approx(meta["best_mae"], abs=1e-2)
    # The same search again writes the same bytes (the run time is returned, not kept in the file).
    run_search(config, tmp_path / "again.npz", progress=False)
    assert (tmp_path / "again.npz").read_bytes() == out.read_bytes()


def test_every_algorithm_is_known_to_nlopt():
    for name in ALGORITHMS:
        assert hasattr(nlopt, name)


def test_a_start_that_leaves_every_pixel_invalid_is_warned(scene_dir, tmp_path):
    from capture_sim.errors import DisplexWarning

    config = SearchConfig(family="olat", num_patterns=2, maxeval=1, scenes=(str(scene_dir),), scene_size=SIZE, pixels_per_scene=100)
    with pytest.warns(DisplexWarning, match="every pixel"):
        run_search(config, tmp_path / "olat.npz", progress=False)
    good = SearchConfig(family="tri_complementary", num_patterns=2, maxeval=1, scenes=(str(scene_dir),), scene_size=SIZE, pixels_per_scene=100)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DisplexWarning)
        run_search(good, tmp_path / "tri.npz", progress=False)


@pytest.mark.parametrize("algorithm", ["GN_CRS2_LM", "GN_ESCH"])
def test_same_seed_same_search(algorithm):
    """Stochastic algorithms repeat their evaluations exactly for a seed, and differ for another."""
    def points(seed):
        return [tuple(x) for x, _ in minimise(quadratic, np.zeros(3), LOW, HIGH, algorithm, maxeval=15, seed=seed).history]

    assert points(4) == points(4) and points(4) != points(5)


@pytest.mark.parametrize("algorithm", ["GN_CRS2_LM", "LN_BOBYQA"])
def test_ctrl_c_inside_the_objective_comes_out_as_keyboard_interrupt(algorithm):
    """NLopt's C code must not see the interrupt (CRS2 turned it into chained SystemErrors)."""
    calls = []

    def interrupted(x, need_gradient):
        calls.append(x)
        if len(calls) == 5:
            raise KeyboardInterrupt
        return quadratic(x, need_gradient)

    with pytest.raises(KeyboardInterrupt):
        minimise(interrupted, np.zeros(3), LOW, HIGH, algorithm, maxeval=50, seed=0)
    assert len(calls) == 5


@pytest.mark.parametrize("algorithm", ["LN_BOBYQA", "LN_COBYLA"])
def test_too_many_parameters_for_a_quadratic_algorithm_fail_before_the_scenes(monkeypatch, tmp_path, algorithm):
    """tri_random at M = 8 has 9 * 16 * 3 * 8 = 3456 parameters: refused before any scene is made."""
    def no_scenes(*args, **kwargs):
        raise AssertionError("prepare_scenes was called")

    monkeypatch.setattr(train.search, "prepare_scenes", no_scenes)
    config = SearchConfig(family="tri_random", num_patterns=8, algorithm=algorithm, maxeval=3)
    with pytest.raises(InputError, match="3456 parameters") as refused:
        run_search(config, tmp_path / "big.npz", progress=False)
    assert not any(tmp_path.iterdir())
    # minimise refuses with the very same message.
    size = MAX_QUADRATIC_PARAMETERS + 1
    with pytest.raises(InputError) as also_refused:
        minimise(quadratic, np.zeros(size), -np.ones(size), np.ones(size), algorithm, maxeval=3)
    assert str(also_refused.value) == str(refused.value).replace("3456", str(size))
    # A gradient algorithm takes the same search on to the scenes.
    with pytest.raises(AssertionError, match="prepare_scenes"):
        run_search(SearchConfig(family="tri_random", num_patterns=8, algorithm="LD_MMA", maxeval=3), tmp_path / "big.npz", progress=False)


def test_a_refused_search_leaves_an_earlier_partial_trace(scene_dir, tmp_path):
    out = tmp_path / "best.npz"
    partial = partial_trace_path(out)
    partial.write_text("index,lo,mae_deg,best_mae_deg\n0,0.1,9.0,9.0\n")
    no_normals = tmp_path / "bare"
    no_normals.mkdir()
    scene = synthesize_scene("sphere", "lambertian", load_rig(), SIZE[0], SIZE[1], seed=0)
    save_scene(dataclasses.replace(scene, normal=None), no_normals / "sphere.npz")
    with pytest.raises(InputError, match="no ground-truth normals"):
        run_search(SearchConfig(maxeval=2, scenes=(str(no_normals),), scene_size=SIZE), out, progress=False)
    assert partial.read_text().startswith("index,lo")


def test_interrupted_search_leaves_a_partial_trace_and_the_finished_run_untouched(scene_dir, tmp_path, monkeypatch):
    """Ctrl-C after 13 evaluations: all 13 are in .trace.partial.csv, and the files of the earlier
    finished run with the same --out (trace, chart, patterns, config) are unchanged; so they are
    after a Ctrl-C while the outputs of a search that has finished its evaluations are written."""
    out = tmp_path / "best.npz"
    partial = tmp_path / "best.trace.partial.csv"
    assert partial_trace_path(out) == partial and ("partial trace", partial) in output_files(out)
    partial.write_text("a stale partial trace of an older interrupted run\n")
    config = SearchConfig(family="tri_complementary", num_patterns=2, maxeval=12, scenes=(str(scene_dir),), scene_size=SIZE, pixels_per_scene=100)
    run_search(config, out, progress=False)
    assert not partial.exists()
    finished = {name: (tmp_path / name).read_bytes() for name in ("best.npz", "best.trace.csv", "best.trace.png", "best.config.json")}
    assert len(finished["best.trace.csv"].decode().splitlines()) == 1 + 12

    evaluated = []
    evaluate = PatternObjective.__call__

    def interrupted(self, vector, need_gradient):
        if len(evaluated) == 13:
            raise KeyboardInterrupt
        evaluated.append(vector.copy())
        return evaluate(self, vector, need_gradient)

    monkeypatch.setattr(PatternObjective, "__call__", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_search(dataclasses.replace(config, maxeval=30), out, progress=False)
    assert len(evaluated) == 13
    rows = list(csv.DictReader(partial.read_text().splitlines()))
    assert [int(row["index"]) for row in rows] == list(range(13))
    names = list(rows[0])[1:-2]
    assert np.array_equal([[float(row[name]) for name in names] for row in rows], evaluated)
    assert {name: (tmp_path / name).read_bytes() for name in finished} == finished
    monkeypatch.setattr(PatternObjective, "__call__", evaluate)

    def chart_interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("train.figures.save_figure", chart_interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_search(dataclasses.replace(config, maxeval=3, seed=1), out, progress=False)
    assert {name: (tmp_path / name).read_bytes() for name in finished} == finished
    assert len(partial.read_text().splitlines()) == 1 + 3 and not list(tmp_path.glob(".staging*"))


def test_a_second_search_on_the_same_output_is_refused(scene_dir, tmp_path):
    from capture_sim.atomic import exclusive_output

    out = tmp_path / "s.npz"
    with exclusive_output(out, "search"):
        with pytest.raises(InputError, match="another search is writing"):
            run_search(SearchConfig(maxeval=2, scenes=(str(scene_dir),), scene_size=SIZE), out, progress=False)
    assert not any(tmp_path.iterdir())


def test_auto_exposure_carries_its_gradient_into_the_search_objective(scene_dir, monkeypatch):
    """Auto exposure e = target / (noise-free capture at the percentile) is a function of the
    patterns: its gradient is exact (gradcheck, float64), its value auto exposure's, and the
    objective's gradient goes through it (a brighter set is exposed for less time)."""
    from capture_sim.scene import load_scene
    from patterns.families import make_patterns
    from train.capture import exposure_with_gradient, scene_exposure

    rig = load_rig()
    pixels = scene_pixels(load_scene(scene_dir / "blob.npz"), rig, require_normals=True)
    pixels = dataclasses.replace(pixels, transport=dataclasses.replace(pixels.transport, matrix=pixels.transport.matrix.double()))
    patterns = make_patterns("mono_gradient", 4).double().clamp(0.05, 0.95).requires_grad_()
    assert float(exposure_with_gradient(pixels, patterns).detach()) == scene_exposure(pixels, patterns.detach())
    assert torch.autograd.gradcheck(lambda p: exposure_with_gradient(pixels, p), (patterns,), eps=1e-7, atol=1e-9)

    calls = []
    monkeypatch.setattr(train.search, "exposure_with_gradient", lambda *args: calls.append(1) or exposure_with_gradient(*args))
    scenes = prepare_scenes((str(scene_dir),), "train", rig, SIZE, 0)
    objective = PatternObjective("tri_complementary", 2, scenes, rig.rows, rig.cols, pixels_per_scene=100)
    x = default_vector("tri_complementary", 2).numpy()
    assert objective(x, True)[0] == objective(x, False)[0] and len(calls) == len(scenes)  # the value bit for bit
    with pytest.raises(InputError, match="floating-point scalar"):
        from capture_sim.simulator import simulate
        simulate(make_patterns("mono_gradient", 4), pixels.transport, rig, exposure=torch.tensor([0.01, 0.02]))
