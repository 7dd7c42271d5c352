"""What a model was trained to understand, and how near a prompt lies to it.

The vocabulary is taken from the training split a denoiser learned from: the actions (content
labels where the dataset has them, each with a sample of its captions), the manner words of its
styles, and every word its captions use. It ships beside the model (vocabulary.json, with the
samples' text-encoder features in vocabulary.safetensors so that loading encodes nothing). Beside the
sample, vocabulary.safetensors holds a caption index: every distinct training caption, reduced to a few
principal components of the text encoder's space, with the length and root speed of its motions, which
the in-place test looks up, and a net fitted to those lengths, which gives the length prior
(salad.models.length_net).

A prompt far from everything trained is still answered, with the nearest thing the model knows;
`PromptCheck.warnings` says so instead of letting it pass silently.
"""
from __future__ import annotations

import json
import math
import re
from collections import OrderedDict
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from ..data.captions import CONTENT_PHRASES, STYLE_PHRASES
from ..data.dataset import read_captions, read_split
from ..data.labels import read_labels
from ..motion.representation import FPS
from ..files import atomic_path, atomic_write_text
from .length_net import LengthNet
from .text import TextEncoder, split_words

VOCABULARY_FILE = "vocabulary.json"
FEATURES_FILE = "vocabulary.safetensors"
EXAMPLES_PER_ACTION = 24
# captions whose motions' speeds (the in-place test) and lengths (nearest_seconds, the length prior of an index
# without a length net) are taken the median of, nearest to the prompt first
LENGTH_NEIGHBOURS = 8
# The neighbours' lengths and the in-place test look the prompt up among every distinct training caption (41,420
# on Bandai), not among the 24-per-action sample: the sample holds one or two captions per style of an
# action, so a manner word finds other actions' captions of the same shape first (an exhausted straight
# walk took its length from exhausted turns, 4 s against 9 real). Validation split, every caption of every
# clip (3,336) against its own motion's length: within +-35% 0.70 (sample) against 0.87 (index), the
# median of each of the 79 action-style groups 0.78 against 0.94 (test split, 10,008 captions: 0.69 / 0.73
# against 0.88 / 0.85). The index keeps INDEX_DIMS principal components in fp16 (5 MB; all 384 dimensions
# score the same at 32 MB).
INDEX_DIMS = 64
# Root speed (m/s) below which the motions of the training captions nearest a prompt count as done in
# place. Per-caption medians in the Bandai training split: raises, waves, bows, calls and gestures
# 0.01-0.20; actions that step or use the legs (punch, dance, kick, slash) 0.22-0.45; walks 0.46 and up.
IN_PLACE_SPEED = 0.25

# A side given to a body part no training caption gives one to is read by the side word alone, which
# the captions tie to the parts they do side: the Bandai captions side only hands and arms, and "a man
# kicks with his right leg" came out as a goodbye in 1-2 of 3 seeds (assets/RESULTS.md, Limitations).
SIDES = ("left", "right")
BODY_PARTS = frozenset({"hand", "arm", "leg", "foot", "feet", "knee", "shoulder", "elbow", "wrist", "fist",
                        "hip", "ankle", "toe", "heel", "thigh"})

# A prompt whose best cosine similarity (mean-pooled text-encoder features) to the training caption
# sample is below this asks for something the model has not learned. With MiniLM on the Bandai
# vocabulary the 54 held-out paraphrases of salad.eval.paraphrases score 0.54-0.94 (three below 0.55)
# and 19 untrained actions 0.35-0.60 (14 below); the untrained ones above it all use a word no
# training caption has, which the word check flags (tests/test_vocabulary.py).
ACTION_SIMILARITY = 0.55
# Share of a prompt's words the tokenizer's or the captions' lexicon must hold to read as English;
# the lexicon is lenient (it holds "une", "con", "la"), so a prompt of 3 or more words must also use
# at least one word of the captions or an English function word.
ENGLISH_SHARE = 0.6
WARNINGS_KEPT = 256
_NON_ASCII_LETTER = re.compile(r"[^\x00-\x7f]")
# Words any request may use that carry no action or manner of their own.
_FUNCTION_WORDS = frozenset("""
a an the and or then while with without to of in on at by for from into onto over under up down is are
was be being been as it its they them their his her he she him someone somebody person people man woman
one two three four five six seven eight nine ten times time once twice again very really just still also
this that these those some few several
""".split())


@dataclass
class Vocabulary:
    actions: dict[str, str]             # action key -> how to name it ("a person kicks")
    examples: list[tuple[str, str]]     # (action key, training caption): the sample prompts are compared with
    styles: list[str]                   # manner words of the trained styles, for messages
    words: frozenset[str]               # every word of the training captions
    source: str = ""
    # seconds of the motions each example caption describes (their median), parallel to examples; empty in
    # vocabularies written before lengths were kept
    durations: tuple[float, ...] = ()
    # mean horizontal root speed (m/s) of those motions (their median), parallel to examples; empty in
    # vocabularies written before speeds were kept
    speeds: tuple[float, ...] = ()
    # every distinct training caption with the median seconds and root speed of its motions: not written
    # to the JSON; save_vocabulary turns it into the caption index
    captions: tuple[tuple[str, float, float], ...] = ()

    def to_json(self) -> dict:
        return {"source": self.source, "actions": self.actions, "examples": [list(e) for e in self.examples],
                "styles": self.styles, "words": sorted(self.words), "durations": list(self.durations),
                "speeds": list(self.speeds)}

    @classmethod
    def from_json(cls, doc: dict, where: str) -> "Vocabulary":
        try:
            vocab = cls(actions=dict(doc["actions"]), examples=[(str(a), str(c)) for a, c in doc["examples"]],
                        styles=[str(s) for s in doc["styles"]], words=frozenset(doc["words"]),
                        source=str(doc.get("source", "")),
                        durations=tuple(float(d) for d in doc.get("durations", ())),
                        speeds=tuple(float(v) for v in doc.get("speeds", ())))
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{where}: not a vocabulary file ({e})") from None
        if vocab.durations and (len(vocab.durations) != len(vocab.examples)
                                or not all(math.isfinite(d) and d > 0 for d in vocab.durations)):
            raise ValueError(f"{where}: {len(vocab.durations)} durations for {len(vocab.examples)} examples, or one "
                             "that is not a positive number of seconds")
        if vocab.speeds and (len(vocab.speeds) != len(vocab.examples)
                             or not all(math.isfinite(v) and v >= 0 for v in vocab.speeds)):
            raise ValueError(f"{where}: {len(vocab.speeds)} speeds for {len(vocab.examples)} examples, or one "
                             "that is not a speed in m/s")
        return vocab


def build_vocabulary(root: str | Path, split: str = "train", per_action: int = EXAMPLES_PER_ACTION,
                     seed: int = 0) -> Vocabulary:
    """The vocabulary of the captions (and labels.json, when present) of `split` under `root`.
    Without labels every distinct caption is its own action."""
    root = Path(root)
    names = read_split(root, split)
    try:
        labels = read_labels(root)
    except FileNotFoundError:
        labels = {}
    by_action: dict[str, list[str]] = {}
    seconds: dict[tuple[str, str], list[float]] = {}     # (action, caption) -> the lengths of its motions
    speeds: dict[tuple[str, str], list[float]] = {}      # ... and their mean root speeds
    styles: set[str] = set()
    words: set[str] = set()
    for name in names:
        path = root / "texts" / f"{name}.txt"
        motion = root / "new_joint_vecs" / f"{name}.npy"
        if not path.is_file() or not motion.is_file():
            continue
        features = np.load(motion, mmap_mode="r")
        n = len(features)
        # channels 1-2: the root's horizontal velocity per frame
        speed = float(np.linalg.norm(np.asarray(features[:, 1:3], dtype=np.float64), axis=-1).mean() * FPS)
        captions = [c.text for c in read_captions(path)]
        for caption in captions:
            words.update(split_words(caption))
        lab = labels.get(name)
        if lab is not None:
            by_action.setdefault(lab.content, []).extend(captions)
            styles.add(lab.style)
        else:
            for caption in captions:
                by_action.setdefault(caption, []).append(caption)
        for caption in captions:
            key = (lab.content if lab is not None else caption, caption)
            seconds.setdefault(key, []).append(n / FPS)
            speeds.setdefault(key, []).append(speed)
    if not by_action:
        raise ValueError(f"{root}: split {split!r} has no captioned motions to take a vocabulary from")
    rng = np.random.default_rng(seed)
    examples = []
    for action in sorted(by_action):
        distinct = sorted(set(by_action[action]))
        picked = rng.permutation(len(distinct))[:per_action]
        examples.extend((action, distinct[i]) for i in sorted(picked))
    actions = {a: (f"a person {CONTENT_PHRASES[a][0].format(poss='their')}" if a in CONTENT_PHRASES else a)
               for a in sorted(by_action)}
    manner = sorted({adv for s in styles for adv in STYLE_PHRASES.get(s, ((), ()))[0] if adv and " " not in adv})
    durations = tuple(round(float(np.median(seconds[e])), 2) for e in examples)
    speed = tuple(round(float(np.median(speeds[e])), 3) for e in examples)
    by_caption: dict[str, list[tuple[str, str]]] = {}
    for key in seconds:
        by_caption.setdefault(key[1], []).append(key)
    captions = tuple((c, round(float(np.median([t for k in keys for t in seconds[k]])), 2),
                      round(float(np.median([v for k in keys for v in speeds[k]])), 3))
                     for c, keys in sorted(by_caption.items()))
    return Vocabulary(actions, examples, manner, frozenset(words), source=f"{root.name}/{split}", durations=durations,
                      speeds=speed, captions=captions)


def save_vocabulary(vocab: Vocabulary, encoder: TextEncoder, out: str | Path) -> Path:
    """Write vocabulary.json, the examples' features and the caption index under `out` (a model directory)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tensors = {"pooled": _encode([c for _, c in vocab.examples], encoder).to(torch.float16)}
    if vocab.captions:
        tensors.update(CaptionIndex.build(_encode([c for c, _, _ in vocab.captions], encoder),
                                          [d for _, d, _ in vocab.captions], [v for _, _, v in vocab.captions]).tensors())
    with atomic_path(out / FEATURES_FILE) as tmp:
        save_file(tensors, str(tmp), metadata={"encoder": json.dumps(encoder.spec(), sort_keys=True)})
    atomic_write_text(out / VOCABULARY_FILE, json.dumps(vocab.to_json(), indent=1))
    return out / VOCABULARY_FILE


def _encode(prompts: list[str], encoder: TextEncoder, chunk: int = 64) -> torch.Tensor:
    rows = [encoder.encode(prompts[i:i + chunk]).pooled.cpu() for i in range(0, len(prompts), chunk)]
    return torch.nn.functional.normalize(torch.cat(rows).float(), dim=-1)


def _project(features: torch.Tensor, mean: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    return torch.nn.functional.normalize((features.float() - mean) @ basis, dim=-1)


@dataclass
class CaptionIndex:
    """Training captions as INDEX_DIMS principal components of their unit-length text features, with
    their motions' seconds and root speeds (m/s)."""
    mean: torch.Tensor        # (dim,)
    basis: torch.Tensor       # (dim, k)
    points: torch.Tensor      # (n, k), unit length
    seconds: torch.Tensor     # (n,)
    speeds: torch.Tensor      # (n,)
    # points -> seconds, fitted to these captions (the length prior); None in indexes written before it
    lengths: LengthNet | None = None

    @classmethod
    def build(cls, features: torch.Tensor, seconds, speeds) -> "CaptionIndex":
        mean = features.mean(0)
        centred = (features - mean).double()
        # eigenvectors of the covariance: deterministic, unlike a randomised low-rank solver
        _, vectors = torch.linalg.eigh(centred.T @ centred)
        mean, basis = mean.float(), vectors[:, -min(INDEX_DIMS, len(features)):].flip(-1).float().contiguous()
        # the points as stored (fp16), so a built index answers as the one read back
        points = _project(features, mean, basis).half().float()
        seconds = torch.tensor(seconds, dtype=torch.float32)
        return cls(mean, basis, points, seconds, torch.tensor(speeds, dtype=torch.float32),
                   LengthNet.fit(points, seconds))

    def project(self, features: torch.Tensor) -> torch.Tensor:
        return _project(features, self.mean, self.basis)

    def tensors(self) -> dict[str, torch.Tensor]:
        return {"index_mean": self.mean, "index_basis": self.basis, "index_points": self.points.half(),
                "index_seconds": self.seconds, "index_speeds": self.speeds,
                **(self.lengths.tensors() if self.lengths is not None else {})}

    @classmethod
    def from_tensors(cls, t: dict[str, torch.Tensor], dim: int) -> "CaptionIndex | None":
        """The index in `t` (tensors read from vocabulary.safetensors), or None where there is none or it
        does not fit an encoder of `dim` features."""
        try:
            index = cls(t["index_mean"].float(), t["index_basis"].float(), t["index_points"].float(),
                        t["index_seconds"].float(), t["index_speeds"].float())
        except KeyError:
            return None
        n, k = index.points.shape
        fits = (index.mean.shape == (dim,) and index.basis.shape == (dim, k) and index.seconds.shape == (n,)
                and index.speeds.shape == (n,) and n > 0 and bool(torch.all(index.seconds > 0))
                and bool(torch.all(index.speeds >= 0)))
        if not fits:
            return None
        index.lengths = LengthNet.from_tensors(t, k)
        return index


class PromptCheck:
    """Compares prompts with a vocabulary in `encoder`'s space."""

    def __init__(self, vocab: Vocabulary, encoder: TextEncoder, features: torch.Tensor | None = None,
                 index: CaptionIndex | None = None):
        self.vocab, self.encoder = vocab, encoder
        self._features = features
        self.index = index
        self._lexicon: frozenset[str] | None = None
        self._sided: frozenset[str] | None = None
        self._warned: OrderedDict[str, tuple[str, ...]] = OrderedDict()

    @classmethod
    def load(cls, model_dir: str | Path, encoder: TextEncoder) -> "PromptCheck | None":
        """The check shipped in `model_dir`, or None when it has no vocabulary.json. Features made
        with another text encoder are recomputed (at first use); a caption index made with another
        one is left out (the length prior then looks among the examples)."""
        path = Path(model_dir) / VOCABULARY_FILE
        if not path.is_file():
            return None
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as e:
            raise ValueError(f"{path}: unreadable vocabulary ({e})") from None
        vocab = Vocabulary.from_json(doc, str(path))
        features, index = None, None
        fpath = Path(model_dir) / FEATURES_FILE
        if fpath.is_file():
            # features that do not fit (another encoder, a damaged file) are only a cache: recomputed
            try:
                with safe_open(str(fpath), "pt") as f:
                    spec = (f.metadata() or {}).get("encoder")
                stored = load_file(str(fpath))
            except (OSError, ValueError, SafetensorError):
                spec, stored = None, {}
            if spec == json.dumps(encoder.spec(), sort_keys=True):
                pooled = stored.get("pooled")
                if pooled is not None and pooled.shape == (len(vocab.examples), encoder.dim):
                    features = pooled.float()
                index = CaptionIndex.from_tensors(stored, encoder.dim)
        return cls(vocab, encoder, features, index)

    @property
    def features(self) -> torch.Tensor:
        if self._features is None:
            self._features = _encode([c for _, c in self.vocab.examples], self.encoder)
        return self._features

    def _query(self, prompt: str) -> torch.Tensor:
        # compared on the CPU, where the stored vocabulary features are
        return torch.nn.functional.normalize(self.encoder.encode([prompt]).pooled.float().cpu(), dim=-1)[0]

    def nearest(self, prompt: str, k: int = 3) -> list[tuple[str, float]]:
        """The `k` trained actions nearest to `prompt`: (how to name it, cosine similarity), best first."""
        q = self._query(prompt)
        sims = self.features @ q
        best: dict[str, float] = {}
        for (action, _), s in zip(self.vocab.examples, sims.tolist()):
            best[action] = max(best.get(action, -1.0), s)
        ranked = sorted(best.items(), key=lambda kv: -kv[1])[:k]
        return [(self.vocab.actions.get(a, a), round(s, 3)) for a, s in ranked]

    def _nearest_median(self, prompt: str, quantity: str, k: int) -> float | None:
        """The median `quantity` ("seconds" or "speeds") of the motions of the `k` training captions
        nearest to `prompt`: in the caption index, or among the examples where the model ships none;
        None when neither keeps that quantity."""
        if self.index is not None:
            values = getattr(self.index, quantity)
            sims = self.index.points @ self.index.project(self._query(prompt)[None])[0]
        else:
            values = torch.tensor(self.vocab.durations if quantity == "seconds" else self.vocab.speeds)
            if not len(values):
                return None
            sims = self.features @ self._query(prompt)
        nearest = torch.topk(sims, min(k, len(values))).indices
        return float(np.median(values[nearest].numpy()))

    def length_prior(self, prompt: str) -> float | None:
        """Seconds a motion for `prompt` lasts in the training data: the caption index's length net where it has
        one, else nearest_seconds (None when the vocabulary keeps no lengths)."""
        if self.index is not None and self.index.lengths is not None:
            return float(self.index.lengths(self.index.project(self._query(prompt)[None]))[0])
        return self.nearest_seconds(prompt)

    def nearest_seconds(self, prompt: str, k: int = LENGTH_NEIGHBOURS) -> float | None:
        """The median length of the motions of the `k` training captions nearest to `prompt` (None when the
        vocabulary keeps no lengths)."""
        return self._nearest_median(prompt, "seconds", k)

    def in_place(self, prompt: str, k: int = LENGTH_NEIGHBOURS) -> bool | None:
        """Whether `prompt` asks for an action done in place: the median root speed of the motions of the
        `k` training captions nearest to it is below IN_PLACE_SPEED (None when the vocabulary keeps no speeds)."""
        speed = self._nearest_median(prompt, "speeds", k)
        return None if speed is None else speed < IN_PLACE_SPEED

    def unknown_words(self, prompt: str) -> list[str]:
        """Words of `prompt` no training caption uses (numbers and function words aside)."""
        out = []
        for w in split_words(prompt):
            if w in self.vocab.words or w in _FUNCTION_WORDS or w.isdigit() or w in out:
                continue
            out.append(w)
        return out

    def sided_parts(self) -> frozenset[str]:
        """The body parts the example captions give a side ("left hand" -> "hand")."""
        if self._sided is None:
            self._sided = frozenset(_part(b) for _, c in self.vocab.examples
                                    for a, b in pairwise(split_words(c)) if a in SIDES and _part(b) in BODY_PARTS)
        return self._sided

    def unsided_parts(self, prompt: str) -> list[str]:
        """The "side part" phrases of `prompt` ("right leg") whose part no example caption gives a side."""
        out = []
        for a, b in pairwise(split_words(prompt)):
            if a in SIDES and _part(b) in BODY_PARTS - self.sided_parts() and f"{a} {b}" not in out:
                out.append(f"{a} {b}")
        return out

    def _english(self, words: list[str]) -> bool:
        if self._lexicon is None:
            tokenizer = getattr(self.encoder, "tokenizer", None)
            vocab = tokenizer.get_vocab() if hasattr(tokenizer, "get_vocab") else {}
            self._lexicon = frozenset(w for w in vocab if w.isalpha()) | self.vocab.words | _FUNCTION_WORDS
        if not words:
            return True
        known = sum(w in self._lexicon or w.rstrip("s") in self._lexicon for w in words)
        anchored = any(w in self.vocab.words or w in _FUNCTION_WORDS for w in words)
        return known / len(words) >= ENGLISH_SHARE and (anchored or len(words) < 3)

    def warnings(self, prompt: str) -> list[str]:
        """What a user should know about how `prompt` will be understood; empty when all is well.
        Kept for the last WARNINGS_KEPT prompts: every decoded motion asks again (a millisecond each)."""
        found = self._warned.get(prompt)
        if found is None:
            found = self._warned[prompt] = tuple(self._warnings(prompt))
            while len(self._warned) > WARNINGS_KEPT:
                self._warned.popitem(last=False)
        return list(found)

    def _warnings(self, prompt: str) -> list[str]:
        words = split_words(prompt)
        near = self.nearest(prompt, k=1)
        name, sim = near[0] if near else ("", 0.0)
        closest = f"closest known motion: '{name}' (similarity {sim:.2f})"
        if _NON_ASCII_LETTER.search(prompt) or not self._english(words):
            return [f"the prompt does not read as English, the only language the model was trained on; "
                    f"{closest}"]
        out = []
        if sim < ACTION_SIMILARITY:
            out.append(f"this asks for an action the model was not trained on, so it will do something else; "
                       f"{closest}")
        unknown = self.unknown_words(prompt)
        if unknown:
            listed = ", ".join(f"'{w}'" for w in unknown)
            # an unknown adverb is most likely a manner the user wants: say which ones exist
            styles = ", ".join(self.vocab.styles) if any(w.endswith("ly") for w in unknown) else ""
            out.append(f"the model never saw the word{'s' if len(unknown) > 1 else ''} {listed} in training "
                       f"and may ignore {'them' if len(unknown) > 1 else 'it'}"
                       + (f" (manner words it knows: {styles})" if styles else ""))
        for phrase in self.unsided_parts(prompt):
            side, known = phrase.split()[0], ", ".join(sorted(self.sided_parts()))
            where = f"captions give a side only to: {known}" if known else "no caption gives a body part a side"
            out.append(f"no training caption names the {phrase} ({where}), so '{side}' may move the motion "
                       f"towards other parts or a turn; better leave the side out")
        return out


def _part(word: str) -> str:
    """A body part's singular ("hands" -> "hand"; "feet" stays, as its own entry)."""
    return word[:-1] if word.endswith("s") and word[:-1] in BODY_PARTS else word
