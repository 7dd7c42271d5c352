import copy
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from salad.models.text import TextFeatures, load_text_encoder, split_words
from salad.models.torchvision_compat import ensure_torchvision_importable, import_open_clip

REPO = Path(__file__).resolve().parents[1]
TINY_ARCH = "salad-test-tiny-clip"


@pytest.fixture(scope="module")
def minilm():
    return load_text_encoder()


def _check_layout(f: TextFeatures, dim: int, prompts: list[str]) -> None:
    b = len(prompts)
    lengths = f.mask.sum(1)
    assert f.tokens.dtype == torch.float32 and f.tokens.shape == (b, int(lengths.max()), dim)
    assert f.mask.dtype == torch.bool and f.mask.shape == f.tokens.shape[:2]
    assert f.token_words.dtype == torch.long and f.token_words.shape == f.mask.shape
    assert f.pooled.dtype == torch.float32 and f.pooled.shape == (b, dim)
    assert len(f.words) == b
    for i in range(b):
        n = int(lengths[i])
        assert f.mask[i, :n].all() and not f.mask[i, n:].any()  # real tokens first, then padding
        assert f.token_words[i, 0] == -1 and f.token_words[i, n - 1] == -1  # start / end tokens
        assert (f.token_words[i, n:] == -1).all()
        assert (f.tokens[i, n:] == 0).all()
        assert int(f.token_words[i].max()) < len(f.words[i])
    assert torch.isfinite(f.tokens).all() and torch.isfinite(f.pooled).all()


# ---------------------------------------------------------------------------------------------------------
# word splitting
# ---------------------------------------------------------------------------------------------------------
def test_split_words_punctuation():
    assert split_words("A person waves their LEFT hand.") == ["a", "person", "waves", "their", "left", "hand"]
    assert split_words("the person's left-hand, then   jumps!") == ["the", "person's", "left-hand", "then", "jumps"]
    assert split_words("walks 3 steps; turns (quickly)") == ["walks", "3", "steps", "turns", "quickly"]
    assert split_words("") == [] and split_words("  ,. ") == []


# ---------------------------------------------------------------------------------------------------------
# MiniLM
# ---------------------------------------------------------------------------------------------------------
def test_minilm_shapes_and_masks(minilm):
    prompts = ["a person waves their left hand", "", "a person walks"]
    f = minilm.encode(prompts)
    assert minilm.dim == 384 and minilm.name == "minilm"
    _check_layout(f, 384, prompts)
    assert f.mask.sum(1).tolist() == [8, 2, 5]


def test_minilm_word_alignment(minilm):
    prompt = "a person waves their left hand"
    f = minilm.encode([prompt])
    assert f.words[0] == ["a", "person", "waves", "their", "left", "hand"]
    assert f.token_words[0].tolist() == [-1, 0, 1, 2, 3, 4, 5, -1]
    assert f.token_indices(0, f.words[0].index("waves")) == [3]
    assert f.token_indices(0, f.words[0].index("left")) == [5]


def test_minilm_subwords_and_punctuation(minilm):
    prompt = "The person's left-hand, then cartwheels"
    f = minilm.encode([prompt])
    words = f.words[0]
    assert words == ["the", "person's", "left-hand", "then", "cartwheels"]
    ids = minilm.tokenizer(prompt)["input_ids"]
    pieces = minilm.tokenizer.convert_ids_to_tokens(ids)
    owners = f.token_words[0, :len(ids)].tolist()
    by_word = {w: [p for p, o in zip(pieces, owners) if o == i] for i, w in enumerate(words)}
    assert by_word["person's"] == ["person", "'", "s"]
    assert by_word["left-hand"] == ["left", "-", "hand"]
    assert len(by_word["cartwheels"]) > 1 and "".join(by_word["cartwheels"]).replace("#", "") == "cartwheels"
    assert owners[pieces.index(",")] == -1  # separators belong to no word
    # a word's tokens are contiguous
    for i in range(len(words)):
        pos = f.token_indices(0, i)
        assert pos == list(range(pos[0], pos[-1] + 1))


def test_minilm_empty_prompt(minilm):
    f = minilm.encode([""])
    assert f.words == [[]]
    assert f.mask.tolist() == [[True, True]]
    assert f.token_words.tolist() == [[-1, -1]]
    assert torch.isfinite(f.pooled).all() and f.pooled.norm() > 0


def test_minilm_cache_identical_and_bounded(minilm):
    prompts = ["a person jumps twice", "someone crawls on the floor", "a person jumps twice"]
    first = minilm.encode(prompts)
    hits = minilm.cache_info()["hits"]
    second = minilm.encode(prompts)
    assert minilm.cache_info()["hits"] == hits + 2  # duplicates within a call are encoded once
    assert torch.equal(first.tokens, second.tokens) and torch.equal(first.pooled, second.pooled)
    assert torch.equal(first.tokens[0], first.tokens[2])
    second.tokens.zero_()  # callers own the returned tensors; the cache must not change
    assert torch.equal(minilm.encode(prompts).tokens, first.tokens)

    small = load_text_encoder(cache_size=3)
    distinct = [f"a person walks {n} steps" for n in ("one", "two", "three", "four", "five")]
    together = small.encode(distinct)  # more distinct prompts than the cache holds, in one call
    assert small.cache_info()["size"] == 3
    assert together.words[0] == ["a", "person", "walks", "one", "steps"]
    misses = small.cache_info()["misses"]
    small.encode(distinct[-1:])
    assert small.cache_info()["misses"] == misses  # most recent kept
    small.encode(distinct[:1])
    assert small.cache_info()["misses"] == misses + 1  # oldest evicted
    assert small.cache_info()["size"] == 3


def test_minilm_batch_composition_does_not_change_features(minilm):
    alone = load_text_encoder(cache_size=8)
    a = alone.encode(["a person kicks"])
    b = minilm.encode(["a person slowly walks in a circle and then sits down on a chair", "a person kicks"])
    n = int(a.mask.sum())
    assert torch.allclose(a.tokens[0, :n], b.tokens[1, :n], atol=1e-5)
    assert torch.allclose(a.pooled[0], b.pooled[1], atol=1e-5)
    assert not b.mask[1, n:].any()


def test_minilm_semantics(minilm):
    f = minilm.encode(["a person walks forward", "someone is walking", "a person waves their right hand"])
    p = F.normalize(f.pooled, dim=-1)
    assert float(p[0] @ p[1]) > float(p[0] @ p[2]) + 0.1


def test_minilm_truncation(minilm):
    long_prompt = " ".join(["a person walks forward and then turns around"] * 30)
    f = minilm.encode([long_prompt, "a person sits"])
    assert int(f.mask[0].sum()) == minilm.max_tokens == f.tokens.shape[1]
    assert f.token_words[0, minilm.max_tokens - 1] == -1  # the end token survives truncation
    assert len(f.words[0]) == 240  # words are the prompt's, even those cut from the tokens
    assert int(f.token_words[0].max()) < 240


def test_minilm_unknown_words(minilm):
    assert minilm.unknown_words("a person waves their left hand") == []
    assert minilm.unknown_words("a person waves \U0001F642 happily") == ["\U0001F642"]


def test_minilm_spec_round_trip(minilm):
    spec = minilm.spec()
    assert json.loads(json.dumps(spec)) == spec
    again = load_text_encoder({**spec, "max_tokens": 32})
    assert again.max_tokens == 32 and again.dim == 384
    with pytest.raises(ValueError, match="384"):
        load_text_encoder({**spec, "dim": 512})


def test_minilm_is_frozen(minilm):
    assert not any(p.requires_grad for p in minilm.parameters())
    minilm.train()
    assert not minilm.training and not minilm.model.training
    f = minilm.encode(["a person runs"])
    assert not f.tokens.requires_grad
    # models holding the encoder get deep-copied (e.g. for weight averaging): the copy works on its own
    twin = copy.deepcopy(minilm)
    assert twin.cache_info()["size"] == 0
    assert torch.allclose(twin.encode(["a person runs"]).tokens, f.tokens, atol=1e-6)


# ---------------------------------------------------------------------------------------------------------
# spec errors
# ---------------------------------------------------------------------------------------------------------
def test_bad_specs(minilm, tmp_path):
    with pytest.raises(ValueError, match="unknown text encoder spec 'bert'"):
        load_text_encoder("bert")
    with pytest.raises(ValueError, match="openclip:<arch>:<weights.safetensors>"):
        load_text_encoder("openclip:ViT-B-32")
    with pytest.raises(ValueError, match="openclip:<arch>:<weights.safetensors>"):
        load_text_encoder("openclip::/x.safetensors")
    with pytest.raises(FileNotFoundError, match="nowhere.safetensors"):
        load_text_encoder(f"openclip:ViT-B-32:{tmp_path / 'nowhere.safetensors'}")
    with pytest.raises(ValueError, match="unknown kind 'bert'"):
        load_text_encoder({"kind": "bert"})
    with pytest.raises(ValueError, match="unexpected keys"):
        load_text_encoder({"kind": "minilm", "layers": 3})
    with pytest.raises(ValueError, match="'weights'"):
        load_text_encoder({"kind": "openclip", "arch": "ViT-B-32"})
    with pytest.raises(ValueError, match="max_tokens"):
        load_text_encoder({"kind": "minilm", "max_tokens": 4096})
    with pytest.raises(TypeError):
        load_text_encoder(7)
    with pytest.raises(TypeError, match="list of prompt strings"):
        minilm.encode("a person walks")
    with pytest.raises(TypeError, match="prompt 1"):
        minilm.encode(["a person walks", None])


# ---------------------------------------------------------------------------------------------------------
# OpenCLIP with a tiny random checkpoint
# ---------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory):
    from safetensors.torch import save_file

    open_clip = import_open_clip()
    root = tmp_path_factory.mktemp("tiny_clip")
    cfg = {"embed_dim": 32,
           "vision_cfg": {"image_size": 32, "layers": 1, "width": 64, "patch_size": 16},
           "text_cfg": {"context_length": 77, "vocab_size": 49408, "width": 64, "heads": 4, "layers": 2}}
    (root / f"{TINY_ARCH}.json").write_text(json.dumps(cfg))
    open_clip.add_model_config(root / f"{TINY_ARCH}.json")
    torch.manual_seed(0)
    model = open_clip.create_model(TINY_ARCH, pretrained=None).eval()
    state = {k: v.contiguous() for k, v in model.state_dict().items()}
    full = root / "tiny_full.safetensors"
    save_file(state, str(full))
    text_only = root / "tiny_text.safetensors"
    save_file({"text." + k: v for k, v in state.items() if not k.startswith("visual.") and k != "logit_scale"},
              str(text_only))
    return {"model": model, "full": full, "text_only": text_only, "root": root,
            "tokenizer": open_clip.get_tokenizer(TINY_ARCH), "state": state}


def test_openclip_tiny_features(tiny_clip):
    enc = load_text_encoder(f"openclip:{TINY_ARCH}:{tiny_clip['full']}")
    prompts = ["a person waves their left hand", "", "the person's left-hand, then cartwheels"]
    f = enc.encode(prompts)
    assert enc.dim == 64 and enc.max_tokens == 77 and enc.name == f"openclip:{TINY_ARCH}"
    _check_layout(f, 64, prompts)
    assert f.words[0] == ["a", "person", "waves", "their", "left", "hand"]
    assert f.token_words[0, :8].tolist() == [-1, 0, 1, 2, 3, 4, 5, -1]
    assert f.mask[1].sum() == 2 and f.words[1] == []
    assert f.words[2] == ["the", "person's", "left-hand", "then", "cartwheels"]
    assert len(f.token_indices(2, 2)) == 3  # left, -, hand
    assert enc.unknown_words("anything \U0001F642") == []

    tok = tiny_clip["tokenizer"]
    for p in prompts:  # word-by-word tokenization equals tokenizing the whole prompt
        assert enc.token_ids(p)[0] == [tok.sot_token_id] + tok.encode(p) + [tok.eot_token_id]

    # the pooled end-of-text feature, projected, is exactly open_clip's own text embedding
    model = tiny_clip["model"]
    with torch.no_grad():
        reference = model.encode_text(tok(prompts))
    assert torch.allclose(f.pooled @ model.text_projection, reference, atol=1e-5)
    spec = enc.spec()
    assert spec["kind"] == "openclip" and spec["arch"] == TINY_ARCH and json.loads(json.dumps(spec)) == spec


def test_openclip_deterministic_and_text_only(tiny_clip):
    prompts = ["a person jumps", "someone walks in a circle"]
    a = load_text_encoder(f"openclip:{TINY_ARCH}:{tiny_clip['full']}").encode(prompts)
    b = load_text_encoder({"kind": "openclip", "arch": TINY_ARCH, "weights": str(tiny_clip["text_only"])}).encode(prompts)
    assert torch.equal(a.tokens, b.tokens) and torch.equal(a.pooled, b.pooled)
    assert torch.equal(a.token_words, b.token_words)


def test_openclip_truncation(tiny_clip):
    enc = load_text_encoder({"kind": "openclip", "arch": TINY_ARCH, "weights": str(tiny_clip["full"]),
                             "max_tokens": 20})
    f = enc.encode([" ".join(["a person walks forward"] * 20)])
    assert f.tokens.shape == (1, 20, 64) and f.mask.all()
    ids, owners, _ = enc.token_ids(" ".join(["a person walks forward"] * 20))
    assert ids[-1] == tiny_clip["tokenizer"].eot_token_id and owners[-1] == -1


def test_openclip_refuses_bad_weights(tiny_clip, tmp_path):
    from safetensors.torch import save_file

    pickled = tmp_path / "weights.bin"
    pickled.write_bytes(b"PK\x03\x04 not opened")
    with pytest.raises(ValueError, match="weights.bin.*safetensors"):
        load_text_encoder(f"openclip:{TINY_ARCH}:{pickled}")
    fake = tmp_path / "fake.safetensors"
    fake.write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match="fake.safetensors: not a safetensors file"):
        load_text_encoder(f"openclip:{TINY_ARCH}:{fake}")
    partial = tmp_path / "partial.safetensors"
    save_file({k: v for k, v in tiny_clip["state"].items() if not k.startswith("transformer.resblocks.1.")},
              str(partial))
    with pytest.raises(ValueError, match="partial.safetensors: weights do not match"):
        load_text_encoder(f"openclip:{TINY_ARCH}:{partial}")
    with pytest.raises(ValueError, match="unknown OpenCLIP architecture 'ViT-B-33'.*ViT-B-32"):
        load_text_encoder(f"openclip:ViT-B-33:{tiny_clip['full']}")
    wrong_size = tmp_path / "wide.safetensors"
    save_file({k: (torch.zeros(v.shape[0], 2 * v.shape[1]) if k == "token_embedding.weight" else v)
               for k, v in tiny_clip["state"].items()}, str(wrong_size))
    with pytest.raises(ValueError, match="wide.safetensors: weights do not fit"):
        load_text_encoder(f"openclip:{TINY_ARCH}:{wrong_size}")


# ---------------------------------------------------------------------------------------------------------
# torchvision import workaround
# ---------------------------------------------------------------------------------------------------------
def _run(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def test_torchvision_workaround_only_when_needed():
    # in a fresh interpreter: the workaround is applied exactly when the plain import fails that way
    out = _run("""
        try:
            import torchvision
            broken = False
        except RuntimeError as err:
            broken = "operator torchvision::nms does not exist" in str(err)
            assert broken, err
        from salad.models.torchvision_compat import ensure_torchvision_importable, defined_torchvision_ops
        added = ensure_torchvision_importable()
        assert bool(added) == broken, (added, broken)
        assert ensure_torchvision_importable() == []  # second call: nothing more to do
        import open_clip
        assert defined_torchvision_ops() == added
        print("broken" if broken else "fine", added)
    """)
    assert out.startswith(("broken ['nms', 'qnms']", "fine []"))


def test_torchvision_workaround_is_noop_when_import_works():
    # the schemas already exist (as with a working torchvision build): the guarded import must define nothing
    out = _run("""
        import torch
        lib = torch.library.Library("torchvision", "FRAGMENT")
        lib.define("nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
        lib.define("qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
        from salad.models.torchvision_compat import ensure_torchvision_importable, defined_torchvision_ops
        assert ensure_torchvision_importable() == []
        assert defined_torchvision_ops() == []
        print("ok")
    """)
    assert out.strip() == "ok"


def test_torchvision_guard_idempotent_in_process(tiny_clip):
    assert ensure_torchvision_importable() == []


# ---------------------------------------------------------------------------------------------------------
# the training captions' features, kept on disk
# ---------------------------------------------------------------------------------------------------------
def test_cached_text_bank_encodes_once_and_survives_a_bad_or_unwritable_cache(minilm, tmp_path, monkeypatch):
    from salad.models.text_bank import TextBank, cached_text_bank

    calls = []

    class Counting:
        """the real encoder, counting the captions it is asked to encode"""
        dim = minilm.dim

        def spec(self):
            return minilm.spec()

        def encode(self, prompts):
            calls.append(len(prompts))
            return minilm.encode(prompts)

    captions = ["a person walks forward", "someone waves the right hand", "a person walks forward", "a man bows"]
    fresh = cached_text_bank(Counting(), captions, tmp_path / "cache", progress=False, dtype=torch.bfloat16)
    assert sum(calls) == 4 and len(list((tmp_path / "cache").glob("*.safetensors"))) == 1     # "" + 3 distinct
    again = cached_text_bank(Counting(), captions, tmp_path / "cache", progress=False, dtype=torch.bfloat16)
    assert sum(calls) == 4                                                                    # read, not encoded
    for a, b in zip(fresh.tensors(), again.tensors()):
        assert torch.equal(a, b)
    for x, y in zip(fresh.batch(captions[:2], 8), again.batch(captions[:2], 8)):
        assert torch.equal(x, y)
    # other captions or another dtype are another entry, never a wrong one
    other = cached_text_bank(Counting(), captions[:2], tmp_path / "cache", progress=False, dtype=torch.bfloat16)
    assert sum(calls) == 7 and other.captions == TextBank.distinct(captions[:2])
    # a torn file is encoded again and replaced
    for p in (tmp_path / "cache").glob("*.safetensors"):
        p.write_bytes(p.read_bytes()[:100])
    before = sum(calls)
    rebuilt = cached_text_bank(Counting(), captions, tmp_path / "cache", progress=False, dtype=torch.bfloat16)
    assert sum(calls) == before + 4 and torch.equal(rebuilt.flat, fresh.flat)
    cached_text_bank(Counting(), captions, tmp_path / "cache", progress=False, dtype=torch.bfloat16)
    assert sum(calls) == before + 4
    # a cache that cannot be written: encoded as without one
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    plain = cached_text_bank(Counting(), captions, blocked / "cache", progress=False, dtype=torch.bfloat16)
    assert torch.equal(plain.flat, fresh.flat)


def test_cached_text_bank_keeps_the_most_recently_used_entries(minilm, tmp_path, monkeypatch):
    import os

    from salad.models import text_bank

    monkeypatch.setattr(text_bank, "TEXT_CACHE_ENTRIES", 2)
    cache = tmp_path / "cache"
    sets = [["a person walks forward"], ["a man bows"], ["someone waves the right hand"]]

    def entries():
        return set(cache.glob("text-features-*.safetensors"))

    text_bank.cached_text_bank(minilm, sets[0], cache, progress=False)
    first = entries()
    text_bank.cached_text_bank(minilm, sets[1], cache, progress=False)
    second = entries() - first
    for age, p in ((300, next(iter(first))), (200, next(iter(second)))):      # timestamps apart, whatever the fs
        os.utime(p, ns=(0, p.stat().st_mtime_ns - age * 10**9))
    text_bank.cached_text_bank(minilm, sets[0], cache, progress=False)       # read: the first is used again
    text_bank.cached_text_bank(minilm, sets[2], cache, progress=False)
    left = entries()
    assert len(left) == 2 and first <= left and not (second & left)          # the least recently used went
