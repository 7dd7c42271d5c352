"""The studio latency benchmark runs end to end through the API on a small model."""
from app.bench import format_table, run


def test_studio_latency_bench_times_every_request(tiny_model):
    report = run(str(tiny_model), steps=2, sampler="ddim", bf16=False, threads=1)
    for key in ("generate_s", "edit_first_s", "edit_same_source_s"):
        assert report[key] and all(t > 0 for t in report[key]), key
    table = format_table(report)
    assert "generate → video" in table and "edit again, same source" in table
