"""The studio latency benchmark runs end to end through the API on a small model."""
from app.bench import format_table, run


def test_studio_latency_bench_times_every_request(tiny_model):
    from app.bench import ROWS

    report = run(str(tiny_model), steps=2, sampler="auto", precision="auto", threads=1)
    assert report["settings"]["fetch_all"] is False, "the page fetches the videos only"
    # the studio's defaults: the teacher's dpm-sde for text, DDIM for guided control (the model has no student)
    assert [report["settings"][k] for k in ("sampler", "edit_sampler", "control_sampler", "steps", "edit_steps",
                                            "control_steps")] == ["dpm-sde", "dpm-sde", "ddim", 2, 2, 2]
    for _, key, _ in ROWS:
        assert report[key] and all(t > 0 for t in report[key]), key
    for preview, full in (("generate_s", "generate_full_s"), ("edit_first_s", "edit_first_full_s"),
                          ("edit_generated_s", "edit_generated_full_s"), ("control_s", "control_full_s")):
        assert all(f > p for p, f in zip(report[preview], report[full])), "the full video: the preview call and more"
    table = format_table(report)
    for text in ("generate → preview video", "generate → full video", "edit again, same source → preview",
                 "edit this motion → preview", "control (path) → preview video", "word click → heatmap"):
        assert text in table, text
    assert "dpm-sde-2, edit dpm-sde-2, control ddim-2" in table.splitlines()[0]
    # the studio's default precision, as this CPU computes it
    assert report["settings"]["computed"] in ("fp32", "bf16 autocast from 2 rows a forward")
    assert f"{report['settings']['computed']} (auto)" in table.splitlines()[0]
    # the machine's speed, measured around the requests, beside them
    assert len(report["matmul_reference_ms"]) == 2 and all(ms > 0 for ms in report["matmul_reference_ms"])
    assert table.splitlines()[1].startswith("50 fp32 1024² matmuls: ")
    full_row = next(line for line in table.splitlines() if line.startswith("generate → full video"))
    assert full_row.split()[-1] == "-", "the full-video rows have no target"


def test_download_leftovers_are_removed_only_when_empty_recent_and_named_like_them(tmp_path, monkeypatch):
    import os
    import tempfile
    import time

    from app.bench import remove_download_leftovers
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    started = time.time()
    leftover = tmp_path / ("ab" * 20)
    full = tmp_path / ("cd" * 20)
    old = tmp_path / ("ef" * 20)
    other = tmp_path / "not-a-hash"
    for d in (leftover, full, old, other):
        d.mkdir()
    (full / "x.mp4").write_bytes(b"1")
    os.utime(old, (started - 3600, started - 3600))
    assert remove_download_leftovers(started) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([full.name, old.name, other.name])


def test_steps_default_to_the_samplers_and_a_missing_student_is_refused(tiny_model, monkeypatch):
    import pytest

    import app.bench as bench

    seen = []
    monkeypatch.setattr(bench, "run", lambda *args: seen.append(args) or {})
    monkeypatch.setattr(bench, "format_table", lambda report: "")
    assert bench.main([]) == 0
    assert seen[-1][1:3] == (None, "auto"), "the studio's own defaults"
    assert bench.main(["--sampler", "consistency"]) == 0
    assert seen[-1][1:3] == (None, "consistency"), "steps left to the pipeline: the sampler's default"
    monkeypatch.undo()
    with pytest.raises(SystemExit, match="cannot benchmark the consistency sampler: .*has no consistency student"):
        run(str(tiny_model), steps=None, sampler="consistency", precision="fp32", threads=1)


def test_a_video_url_is_read_from_either_shape_of_a_video_output():
    import pytest

    from app.bench import _video_url

    url = "http://127.0.0.1:1/gradio_api/file=/x/a_preview.mp4"
    assert _video_url({"path": "/x/a_preview.mp4", "url": url}) == url
    assert _video_url({"video": {"path": "/x/a_preview.mp4", "url": url}, "subtitles": None}) == url
    with pytest.raises(RuntimeError, match="no video URL"):
        _video_url("/x/a_preview.mp4")
