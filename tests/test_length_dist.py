import argparse
import json

import numpy as np
import pytest

from salad.data.dataset import MotionDataset
from salad.data.labels import MotionLabels
from salad.cli.eval import add_eval_length as add_parser
from salad.eval.length_dist import (compare_lengths, earth_movers, evaluate_lengths, generate_auto_length,
                                    js_divergence, length_bins, length_histogram, reachable_length)
from salad.pipeline import load_pipeline


def test_jensen_shannon_on_known_histograms():
    assert js_divergence([0.2, 0.3, 0.5], [0.2, 0.3, 0.5]) == pytest.approx(0.0, abs=1e-12)
    assert js_divergence([1, 0], [0, 1]) == pytest.approx(1.0)
    # M = (0.75, 0.25): 0.5 * (log2(4/3)) + 0.5 * (0.5 log2(2/3) + 0.5 log2(2)) = 0.3113
    expected = 0.5 * np.log2(4 / 3) + 0.5 * (0.5 * np.log2(2 / 3) + 0.5)
    assert js_divergence([1, 0], [0.5, 0.5]) == pytest.approx(expected)
    assert js_divergence([2, 0], [1, 1]) == pytest.approx(expected)      # unnormalised counts work too
    with pytest.raises(ValueError):
        js_divergence([1, 0], [1, 0, 0])


def test_earth_movers_in_frames():
    assert earth_movers([40, 40], [45, 45]) == pytest.approx(5.0)
    assert earth_movers([16, 32, 48], [32, 48, 64]) == pytest.approx(16.0)
    assert earth_movers([10, 20], [20, 10]) == 0.0
    with pytest.raises(ValueError, match="no lengths"):
        earth_movers([], [1])


def test_histograms_bins_and_reachable_lengths():
    edges = length_bins(196, 8)
    assert edges[0] == 0 and edges[-1] >= 196 and np.all(np.diff(edges) == 8)
    h = length_histogram([16, 20, 24, 400], edges)
    assert h.sum() == pytest.approx(1.0) and h[2] == 0.5 and h[3] == 0.25 and h[-1] == 0.25
    assert [reachable_length(n, 196) for n in (5, 17, 63, 196, 250)] == [16, 16, 60, 196, 196]
    rows = compare_lengths([40] * 10, [40] * 5 + [80] * 5, edges)
    assert rows["jsd"] == pytest.approx(js_divergence([1, 0], [0.5, 0.5]))   # one bin vs two halves
    assert rows["emd_frames"] == pytest.approx(20.0) and rows["mean_frames"] == 60.0


def test_eval_length_end_to_end_on_a_tiny_model(tiny_model, tiny_dataset, tmp_path):
    pipe = load_pipeline(tiny_model)
    ds = MotionDataset(tiny_dataset, "test", max_frames=10 ** 9)
    # several captions in one run decode exactly like Pipeline.generate(seconds="model"), row by row
    one = pipe.generate("a person walks forward", seconds="model", seed=7, steps=2, batch=2)
    mixed = generate_auto_length(pipe, ["a person walks forward"] * 2, seed=7, steps=2)
    assert [m.frames for m in mixed] == [m.frames for m in one]
    assert all(np.allclose(a.features, b.features, atol=1e-4) for a, b in zip(mixed, one))
    two = generate_auto_length(pipe, ["a person walks forward", "a person turns left while walking"], seed=7, steps=2)
    assert [m.text for m in two] == ["a person walks forward", "a person turns left while walking"]
    labels = {it.name: MotionLabels("walk", "normal", "none", False, "test") for it in ds.items[:1]}
    res = evaluate_lengths(pipe, ds, samples=5, steps=2, batch=2, labels=labels, seed=3)
    gen, real = np.array(res["lengths"]["generated"]), np.array(res["lengths"]["real"])
    assert len(gen) == len(real) == 5
    assert np.all(gen % 4 == 0) and np.all((16 <= gen) & (gen <= pipe.canvas_frames))
    assert np.all(real % 4 == 0) and np.all(real <= pipe.canvas_frames)
    fixed = res["protocol"]["fixed_length_frames"]
    assert res["rows"]["fixed_mean_length"]["emd_frames"] == pytest.approx(np.abs(real - fixed).mean())
    assert res["rows"]["model"]["emd_frames"] == pytest.approx(earth_movers(real, gen))
    assert set(res["per_content"]) == {"walk"}
    assert res["rows"]["test_redraw"]["jsd"] >= 0 and 0 <= res["generated"]["at_canvas_share"] <= 1
    assert res["generated"]["at_minimum_share"] == pytest.approx(np.mean(gen == 16))

    # the command line writes all three files
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers(dest="command"))
    out = tmp_path / "len"
    a = parser.parse_args(["eval-length", "--data", str(tiny_dataset), "--model", str(tiny_model), "--out", str(out),
                           "--samples", "4", "--steps", "2", "--batch", "4"])
    assert a.func(a) == 0
    doc = json.loads((out / "results.json").read_text())
    assert doc["protocol"]["samples"] == 4 and doc["per_content"] == {}
    assert (out / "lengths.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = (out / "report.md").read_text()
    assert "Fixed mean length" in report and "JSD" in report
    assert sorted(p.name for p in out.iterdir()) == ["lengths.png", "report.md", "results.json"]
    with pytest.raises(ValueError, match="samples"):
        evaluate_lengths(pipe, ds, samples=1)
