"""NLopt search: runs with derivative-free and gradient algorithms, traces every evaluation."""
import csv

import nlopt
import numpy as np
import pytest

import train.nlopt_search as search
from capture_sim.errors import InputError
from capture_sim.rig import load_rig
from capture_sim.scene import save_scene
from capture_sim.synth import synthesize_scene
from train.nlopt_search import SearchConfig, run_search


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("search_scenes")
    save_scene(synthesize_scene("blob", "lambertian", load_rig(), height=16, width=20, seed=1), root / "blob.npz")
    return root


@pytest.mark.parametrize("algorithm", ["LN_BOBYQA", "LD_MMA"])
def test_search_keeps_or_improves_start_and_traces(tmp_path, scene_dir, algorithm):
    config = SearchConfig("tri_complementary", 2, algorithm, maxeval=4, scenes=(str(scene_dir),), pixels_per_scene=100)
    summary = run_search(config, tmp_path / "best.npz", progress=False)
    assert summary["best_mae"] <= summary["start_mae"]
    with open(tmp_path / "best.trace.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == summary["evaluations"] <= 4
    best = [float(row["best_so_far"]) for row in rows]
    assert best == sorted(best, reverse=True) and abs(best[-1] - summary["best_mae"]) < 1e-5
    assert np.load(tmp_path / "best.npz")["patterns"].shape == (2, 9, 16, 3)
    assert (tmp_path / "best.trace.png").is_file()


def test_roundoff_stop_still_returns_best(tmp_path, scene_dir, monkeypatch):
    original = search._Objective.__call__

    def raising(self, x, grad):
        value = original(self, x, grad)
        if len(self.trace) == 3:
            raise nlopt.RoundoffLimited("simulated round-off")
        return value

    monkeypatch.setattr(search._Objective, "__call__", raising)
    config = SearchConfig("tri_complementary", 2, "LN_BOBYQA", maxeval=10, scenes=(str(scene_dir),), pixels_per_scene=100)
    summary = run_search(config, tmp_path / "best.npz", progress=False)
    assert summary["evaluations"] == 3 and "RoundoffLimited" in summary["stop"]
    assert (tmp_path / "best.npz").is_file()


def test_bad_names_raise():
    with pytest.raises(InputError, match="algorithm"):
        SearchConfig("tri_complementary", 2, "LN_MAGIC")
    with pytest.raises(InputError, match="family"):
        SearchConfig("rainbow", 2)
