"""The noise sweep (`displex bench ps --sweep`): structure of its JSON and the error's growth with noise."""
from __future__ import annotations

import json
import math

import pytest

from capture_sim.errors import InputError
from capture_sim.rig import load_rig
from train.bench import noise_sweep, sweep_chart
from train.scene_pixels import scene_pixels
from train.scene_sets import default_split


@pytest.fixture(scope="module")
def tiny_scenes():
    rig = load_rig()
    return [scene_pixels(scene, rig, require_normals=True) for scene in default_split("test", rig, (16, 20))[:2]]


def test_sweep_json_structure_and_error_grows_with_noise(tiny_scenes, tmp_path):
    scales = (0.0, 10.0)
    methods = (("woodham", "olat", 0), ("ps", "mono_gradient", 4))
    document = noise_sweep(tiny_scenes, scales, methods, progress=False)
    assert document["noise_scales"] == [0.0, 10.0]
    assert document["scenes"] == [pixels.name for pixels in tiny_scenes]
    assert [row["patterns"] for row in document["methods"]] == ["olat", "mono_gradient"]
    assert document["methods"][0]["M"] == tiny_scenes[0].rig.num_lights
    for row in document["methods"]:
        for key in ("mae", "median", "invalid_fraction"):
            assert len(row[key]) == len(scales) and all(math.isfinite(value) for value in row[key])
        assert [len(per_scene) for per_scene in row["scene_mae"]] == [len(tiny_scenes)] * len(scales)
        assert row["mae"][0] == pytest.approx(sum(row["scene_mae"][0]) / len(tiny_scenes))
    # The default scenes are not Lambertian, so neither method is exact without noise, but ten
    # times the rig's noise must cost both of them accuracy.
    for row in document["methods"]:
        assert row["mae"][1] > row["mae"][0] + 1.0, row["label"]
    json.dumps(document)  # JSON-serialisable
    chart = tmp_path / "sweep.png"
    sweep_chart(document, chart, "tiny scenes")
    assert chart.stat().st_size > 1000


def test_sweep_rejects_bad_noise_scales(tiny_scenes):
    with pytest.raises(InputError):
        noise_sweep(tiny_scenes, (-1.0,), progress=False)
    with pytest.raises(InputError):
        noise_sweep([], progress=False)


def test_sweep_flag_needs_the_ps_target():
    from train.cli import run

    assert run(["bench", "sim", "--sweep"]) == 2


def test_sweep_writes_its_json_and_chart_together(tiny_scenes, tmp_path, monkeypatch):
    import train.bench as bench
    from train.cli import run

    document = noise_sweep(tiny_scenes, (0.0,), (("ps", "mono_gradient", 4),), progress=False)
    monkeypatch.setattr(bench, "noise_sweep", lambda *args, **kwargs: dict(document))
    monkeypatch.setattr(bench, "default_split", lambda *args, **kwargs: [])
    out = tmp_path / "sweep.json"
    bench.run_sweep(out, (16, 20), progress=False)
    assert json.loads(out.read_text())["target"] == "ps_sweep" and out.with_suffix(".png").stat().st_size > 1000
    before = (out.read_bytes(), out.with_suffix(".png").read_bytes())

    def broken_chart(*args):
        raise RuntimeError("no chart")

    monkeypatch.setattr(bench, "sweep_chart", broken_chart)
    with pytest.raises(RuntimeError):
        bench.run_sweep(out, (16, 20), progress=False)
    # A failed chart leaves the earlier run's pair as it was, not a new JSON beside an old chart.
    assert (out.read_bytes(), out.with_suffix(".png").read_bytes()) == before
    assert sorted(path.name for path in tmp_path.iterdir()) == ["sweep.json", "sweep.png"]
