"""End-to-end: the main job on tiny scenes with two learning steps."""
import json

from train.demo import DemoConfig, run_demo


def test_demo_writes_report_results_and_charts(tmp_path):
    config = DemoConfig(pattern_counts=(2,), noise_scales=(0.5, 1.0), train_steps=2, size=(24, 29), families=("tri_complementary", "mono_gradient"), search_evaluations=3)
    document = run_demo(tmp_path, config, progress=False)
    assert {"learned M=2", "tri_complementary M=2", "mono_gradient M=2", "published learned M=2", "searched tri_complementary M=2"} <= set(document["methods"])
    saved = json.loads((tmp_path / "results.json").read_text())
    for method in saved["methods"].values():
        for row in method["by_noise"].values():
            assert 0.0 <= row["mae"] <= 180.0
    report = (tmp_path / "report.md").read_text()
    assert "learned M=2" in report and "ratio" in report
    for chart in ("mae_vs_m.png", "mae_vs_capture_time.png", "mae_vs_compute_time.png", "mae_vs_noise.png", "patterns.png"):
        assert (tmp_path / chart).stat().st_size > 1000
    assert (tmp_path / "patterns" / "learned_M2.npz").is_file()
