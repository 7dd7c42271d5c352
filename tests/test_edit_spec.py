"""EditSpec: the one description of an attention edit that every caller builds."""
from __future__ import annotations

import numpy as np
import pytest

from salad.editing.spec import DEFAULT_SELF_INJECT, DEFAULT_TAU, EDIT_MODES, HOLD_PARTS, MIRROR_PARTS, EditSpec


def test_defaults_and_mode_from_what_is_given():
    assert DEFAULT_TAU == {"swap": 0.8, "refine": 0.0} and DEFAULT_SELF_INJECT == 0.2
    assert EditSpec(target="a person runs").mode == "swap"
    assert EditSpec(mirror="upper").mode == "mirror"
    assert EditSpec(reweight={"walks": 2}).mode == "reweight"
    spec = EditSpec(target="a person runs")
    assert spec.tau is None and spec.self_inject == 0.2 and spec.mirror is None and spec.weights is None
    assert spec.hold == "auto" and EditSpec(mode="mirror", hold=None).hold is None
    assert spec.target_prompt("a person walks") == "a person runs"
    assert EditSpec(mode="mirror").target_prompt("a person walks") == "a person walks"


def test_no_part_means_all_only_when_mirroring():
    assert EditSpec(mode="mirror").mirror == "all"
    assert EditSpec(mode="swap", target="x y").mirror is None
    assert EditSpec(mode="refine", target="x y", mirror="lower").mirror == "lower"


def test_mirror_parts_are_the_skeletons():
    from salad.motion import skeleton as sk
    assert MIRROR_PARTS == tuple(sk.PART_MIRROR_PAIRS)
    assert HOLD_PARTS == tuple(sk.PART_GROUPS)
    assert sorted(sum(sk.PART_GROUPS.values(), ())) == list(range(sk.BODY_PARTS.size))


def test_reweight_is_kept_as_hashable_pairs():
    spec = EditSpec(mode="reweight", reweight={"walks": 2, "fast": -1.5})
    assert spec.reweight == (("walks", 2.0), ("fast", -1.5)) and spec.weights == {"walks": 2.0, "fast": -1.5}
    assert spec == EditSpec(mode="reweight", reweight=(("walks", 2.0), ("fast", -1.5)))
    assert len({spec, EditSpec(mode="reweight", reweight=[("walks", 2.0), ("fast", -1.5)])}) == 1
    assert spec.params(None, "lower") == {"mode": "reweight", "tau": None, "reweight": {"walks": 2.0, "fast": -1.5},
                                          "mirror": None, "self_inject": 0.2, "hold": "lower"}


@pytest.mark.parametrize("kwargs, message", [
    (dict(mode="paint"), "mode must be one of " + ", ".join(EDIT_MODES)),
    (dict(), "needs a mode"),
    (dict(tau=0.5), "needs a mode"),
    (dict(mode="swap"), "swap needs a target prompt"),
    (dict(mode="refine"), "refine needs a target prompt"),
    (dict(mode="reweight"), "reweight needs words and scales"),
    (dict(mode="mirror", mirror="left"), "mirror part must be one of lower, upper, all"),
    (dict(target="x", tau=1.5), r"tau must be in \[0, 1\]"),
    (dict(target="x", tau=float("nan")), r"tau must be in \[0, 1\]"),
    (dict(mode="mirror", self_inject=-0.1), r"self-attention injection must be a fraction in \[0, 1\]"),
    (dict(mode="reweight", reweight={"walks": 4}), r"re-weighting scale must be in \[-3, 3\]"),
    (dict(mode="reweight", reweight={"walks": "high"}), "reweight must be a dict of word: scale"),
    (dict(mode="reweight", reweight="walks"), "reweight must be a dict of word: scale"),
    (dict(target=3), "target prompt must be a string"),
    (dict(mode="mirror", hold="legs"), "hold must be one of auto, lower, upper or None"),
])
def test_invalid_edits_say_what_is_wrong(kwargs, message):
    with pytest.raises(ValueError, match=message):
        EditSpec(**kwargs)


def test_from_a_dict_and_from_keyword_arguments():
    assert EditSpec.of({"mirror": "upper"}) == EditSpec(mode="mirror", mirror="upper")
    spec = EditSpec(target="a person runs")
    assert EditSpec.of(spec) is spec
    with pytest.raises(ValueError, match="unknown edit option"):
        EditSpec.of({"mirorr": "upper"})
    with pytest.raises(ValueError, match="EditSpec or a dict"):
        EditSpec.of("mirror")
    assert EditSpec.from_arguments(None, mode="swap", target="x", tau=None, reweight=None, mirror=None,
                                   self_inject=0.2) == EditSpec(mode="swap", target="x")
    assert EditSpec.from_arguments(spec, mode="swap", target=None, tau=None, reweight=None, mirror=None,
                                   self_inject=0.2) is spec
    with pytest.raises(ValueError, match="not both"):
        EditSpec.from_arguments(spec, mode="swap", target=None, tau=0.5, reweight=None, mirror=None, self_inject=0.2)


def test_the_package_exports_it():
    import salad
    assert salad.EditSpec is EditSpec


def test_pipeline_edit_takes_a_spec_or_its_keywords(pipe):
    spec = EditSpec(target="a person runs forward", tau=0.6, reweight={"runs": 1.5})
    by_spec = pipe.edit("a person walks forward", spec=spec, seed=1, seconds=1.2, steps=3)
    pipe.source_runs.clear()        # both batched alike: a replayed source differs in the last float digits
    by_keywords = pipe.edit("a person walks forward", "a person runs forward", tau=0.6, reweight={"runs": 1.5},
                            seed=1, seconds=1.2, steps=3)
    np.testing.assert_array_equal(by_spec.edited.joints, by_keywords.edited.joints)
    assert by_spec.params == by_keywords.params and by_spec.params["tau"] == 0.6
    with pytest.raises(ValueError, match="not both"):
        pipe.edit("a person walks forward", mirror="upper", spec=spec)
