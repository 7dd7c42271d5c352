import json

from salad.bench import bench, format_table, matmul_peak
from salad.precision import bf16_supported


def test_bench_measures_a_model_and_writes_json(tiny_model, tmp_path):
    # the tiny model's canvas is 2 s long; one batch size (2, so that per-motion times divide) keeps it short:
    # each run is a fresh subprocess
    report = bench(tmp_path / "bench.json", models=(str(tiny_model),), batches=(2,), quick=True, seconds=1.6)
    runs = report["runs"]
    assert len(runs) == 2 and {r["batch"] for r in runs} == {2}
    for r in runs:
        assert "error" not in r, r
        if "skipped" in r:
            continue
        assert r["ms_per_motion"] > 0 and r["achieved_gflop_s"] > 0 and r["peak_rss_mb"] > 100
    peak = json.loads((tmp_path / "bench.json").read_text())["machine"]["matmul_peak_gflop_s"]
    assert peak["fp32"] > 1
    # a CPU without native bf16 gets no bf16 peak (emulated, it took minutes) and no bf16 runs
    assert (peak["bf16"] is None) == (not bf16_supported())
    assert all("skipped" in r for r in runs if r["precision"] == "bf16") or bf16_supported()
    assert "ms/motion" in format_table(report)


def test_matmul_peak_is_positive():
    assert matmul_peak(__import__("torch").float32, n=256, repeats=2) > 0.1


def test_bench_command_refuses_bad_models_and_batches_before_measuring(tmp_path, cli):
    (tmp_path / "notamodel").mkdir()
    for args, message in ((["--models", "nope"], "neither 'embedded', 'paper' nor a model directory"),
                          (["--models", str(tmp_path / "notamodel")], "notamodel/vae: not a checkpoint directory"),
                          (["--batches", "1,x"], "comma list of batch sizes"),
                          (["--batches", "0"], "must be >= 1")):
        code, err = cli("bench", "--out", str(tmp_path / "b.json"), *args)
        assert code == 2 and message in err, (args, err[-500:])
    assert not (tmp_path / "b.json").exists()


def test_bench_out_takes_a_file_or_a_directory_as_the_eval_commands_do(tmp_path):
    from salad.cli.bench import report_path
    assert report_path(str(tmp_path / "b.json")) == tmp_path / "b.json"
    assert report_path(str(tmp_path / "reports" / "bench-1")) == tmp_path / "reports" / "bench-1" / "bench.json"
    (tmp_path / "odd.json").mkdir()            # a directory that happens to end in .json is still a directory
    assert report_path(str(tmp_path / "odd.json")) == tmp_path / "odd.json" / "bench.json"


def test_the_table_shows_the_compiled_rows_against_the_target():
    report = {"machine": {"matmul_peak_gflop_s": {"fp32": 100.0, "bf16": None}, "cores": 2, "matmul_1024_x50_ms": 500.0},
              "motion": {"seconds": 6.0}, "runs": [],
              "compiled": {"first_call_s": {"consistency": 20.0, "ddim": 15.0},
                           "rows": [{"sampler": "consistency", "steps": 4, "ms_per_motion": 64.6},
                                    {"sampler": "consistency", "steps": 2, "ms_per_motion": 43.3},
                                    {"sampler": "ddim", "steps": 50, "ms_per_motion": 706.0}]}}
    table = format_table(report)
    assert "first call, compiling included: consistency 20 s, ddim 15 s" in table
    assert "consistency 4 step(s): 65 ms/motion, 0.13x the matmul reference (misses the target)" in table
    assert "consistency 2 step(s): 43 ms/motion, 0.09x the matmul reference (meets the target)" in table
    assert "ddim 50 step(s): 706 ms/motion, 1.41x the matmul reference\n" in table + "\n"
    report["compiled"] = {"error": "RuntimeError: no C compiler"}
    assert "RuntimeError: no C compiler" in format_table(report)


def test_the_table_shows_the_studio_standard_sampler_row():
    report = {"machine": {"matmul_peak_gflop_s": {"fp32": 100.0, "bf16": None}, "cores": 2},
              "motion": {"seconds": 6.0}, "runs": [],
              "studio_standard": {"sampler": "dpm-sde", "steps": 25, "ms_per_motion": 431.2}}
    assert "dpm-sde 25 steps: 431 ms/motion" in format_table(report)
    report["studio_standard"] = {"error": "ValueError: no model"}
    assert "ValueError: no model" in format_table(report)
