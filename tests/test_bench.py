import json

from salad.bench import bench, format_table, matmul_peak


def test_bench_measures_a_model_and_writes_json(tiny_model, tmp_path):
    # the tiny model's canvas is 2 s long
    report = bench(tmp_path / "bench.json", models=(str(tiny_model),), batches=(1, 2), quick=True, seconds=1.6)
    runs = report["runs"]
    assert len(runs) == 4
    for r in runs:
        assert "error" not in r, r
        if "skipped" in r:
            continue
        assert r["ms_per_motion"] > 0 and r["achieved_gflop_s"] > 0 and r["peak_rss_mb"] > 100
    assert json.loads((tmp_path / "bench.json").read_text())["machine"]["matmul_peak_gflop_s"]["fp32"] > 1
    assert "ms/motion" in format_table(report)


def test_matmul_peak_is_positive():
    assert matmul_peak(__import__("torch").float32, n=256, repeats=2) > 0.1
