"""The path-following benchmark: its error definitions on known answers, the cases it builds, one run end to end."""
import argparse
import json

import numpy as np
import pytest

from salad.eval import EMBEDDED_EVALUATOR
from salad.cli.eval import add_eval_control as add_parser
from salad.eval.control_bench import (control_error_metrics, controlled_frames, make_cases,
                                      markdown_report, parse_density, parse_joints)
from salad.motion.control import control_errors
from salad.motion.representation import features_to_joints


def test_error_definitions_follow_omnicontrol():
    errors = [np.array([0.1, 0.6, 0.3]),           # fails both thresholds: one location > 50 cm, two > 20 cm
              np.array([0.1, 0.1]),                # passes both
              np.array([0.25])]                    # fails 20 cm only
    m = control_error_metrics(errors)
    assert m["Traj_err_50cm"] == pytest.approx(1 / 3)
    assert m["Traj_err_20cm"] == pytest.approx(2 / 3)
    assert m["Loc_err_50cm"] == pytest.approx((1 / 3 + 0 + 0) / 3)       # per-motion shares, then averaged
    assert m["Loc_err_20cm"] == pytest.approx((2 / 3 + 0 + 1) / 3)
    assert m["Avg_err_m"] == pytest.approx((1.0 / 3 + 0.1 + 0.25) / 3)  # per-motion means, then averaged
    assert m["Max_err_m"] == pytest.approx((0.6 + 0.1 + 0.25) / 3)
    with pytest.raises(ValueError, match="at least one controlled location"):
        control_error_metrics([np.array([])])


def test_density_and_joint_parsing():
    rng = np.random.default_rng(0)
    assert parse_density("100%") == ("percent", 100.0) and parse_density("5") == ("frames", 5.0)
    np.testing.assert_array_equal(controlled_frames(40, parse_density("100%"), rng), np.arange(40))
    quarter = controlled_frames(40, parse_density("25%"), rng)
    assert len(quarter) == 10 and len(set(quarter)) == 10 and (np.diff(quarter) > 0).all()
    assert len(controlled_frames(40, parse_density("2"), rng)) == 2
    for bad in ("0%", "150%", "-1", "many"):
        with pytest.raises(ValueError, match="density"):
            parse_density(bad)
    assert parse_joints("pelvis,left_wrist") == [0, 20] and parse_joints("0") == [0]
    with pytest.raises(ValueError, match="unknown joint 'tail'"):
        parse_joints("pelvis,tail")


def test_cases_control_the_real_trajectory(tiny_dataset):
    from salad.data.dataset import MotionDataset
    ds = MotionDataset(tiny_dataset, "train", max_frames=10 ** 9)
    cases = make_cases(ds, 3, joints=[0, 20], density="25%", seed=1, max_frames=40)
    assert len(cases) == 3 and all(c.frames == 40 for c in cases)
    for c in cases:
        jm = c.signal.joint_mask()
        assert jm[:, [0, 20]].sum() == 2 * 10 and jm.sum() == 20       # both joints at the same 10 frames
        assert c.caption in next(it.captions for it in ds.items if it.name == c.name)
        # the real motion meets its own signal exactly
        assert control_errors(features_to_joints(c.features), c.signal).max() < 1e-5
    again = make_cases(ds, 3, joints=[0, 20], density="25%", seed=1, max_frames=40)
    assert [c.name for c in again] == [c.name for c in cases]         # fixed by the seed


def test_eval_control_end_to_end(tiny_model, tiny_dataset, tmp_path, capsys):
    p = argparse.ArgumentParser(prog="salad")
    add_parser(p.add_subparsers(dest="command", required=True))
    out = tmp_path / "bench"
    a = p.parse_args(["eval-control", "--data", str(tiny_dataset), "--evaluator", str(EMBEDDED_EVALUATOR),
                      "--model", str(tiny_model), "--samples", "2", "--steps", "3", "--strength", "0,2",
                      # the guided rows' deterministic, unprojected, unrefined DDIM, so that strength 0 is the
                      # Unconstrained row again
                      "--ddim-eta", "0", "--cfg-rescale", "0", "--cfg-cutoff", "0", "--projections", "0",
                      "--foot-refine", "0",
                      "--out", str(out)])
    assert a.func(a) == 0
    res = json.loads((out / "results.json").read_text())
    rows = res["rows"]
    assert list(rows) == ["Real motion", "Unconstrained", "Controlled (strength 0)", "Controlled (strength 2)"]
    assert res["protocol"]["samples"] == 2 and res["protocol"]["pool"] == 2
    for name in ("Unconstrained", "Controlled (strength 0)", "Controlled (strength 2)"):
        r = rows[name]
        assert 0 <= r["control"]["Traj_err_50cm"] <= 1 and r["control"]["Avg_err_m"] >= 0
        assert r["AITS_s"] > 0 and len(r["per_sample"]) == 2
        assert 0 <= r["realism"]["R_precision_top1"] <= r["realism"]["R_precision_top3"] <= 1
    # strength 0 is the unconstrained generation again (same noise), guidance brings the pelvis closer
    free, zero, guided = (rows[n]["control"]["Avg_err_m"] for n in
                          ("Unconstrained", "Controlled (strength 0)", "Controlled (strength 2)"))
    assert zero == pytest.approx(free, abs=0.01) and guided < free
    report = (out / "report.md").read_text()
    assert "Traj err 50cm" in report and "AITS" in report and "1.04" in report
    precision = res["protocol"]["unconstrained_sampling"]["precision"]      # what this machine ran in
    assert precision in ("fp32", "bf16 autocast from 2 rows a forward")
    assert f"the Unconstrained row (eta 0, CFG rescale 0, {precision}), the guided rows deterministic" in report
    assert report == markdown_report(res)
    assert "wrote" in capsys.readouterr().out
    bad = p.parse_args(["eval-control", "--data", str(tiny_dataset), "--out", str(tmp_path / "x"),
                        "--joints", "tail"])
    with pytest.raises(ValueError, match="unknown joint"):
        bad.func(bad)
