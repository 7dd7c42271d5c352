"""Token alignment between a source and a target prompt.

Editing maps the source prompt's cross-attention columns onto the target prompt's
tokens. Both prompts are encoded in one batch, so each has its own token positions;
the alignment is expressed as a matrix W (L_source x L_target) with
    edited_target_map = source_map @ W
plus a mask of target tokens that have no source counterpart (new words).
"""
from __future__ import annotations

import difflib
from dataclasses import dataclass

import torch


@dataclass
class TokenAlignment:
    weights: torch.Tensor      # (L, L): column j mixes the source tokens that target token j takes its map from
    inserted: torch.Tensor     # (L,) bool: target tokens with no counterpart in the source
    replaced: torch.Tensor     # (L,) bool: target tokens of a word that differs from its source word (swap)
    source_words: list[str]
    target_words: list[str]
    word_map: list[int]        # for each target word, the aligned source word or -1

    def apply(self, source_map: torch.Tensor) -> torch.Tensor:
        """(..., L) source map -> (..., L) map over the target's token positions."""
        return source_map @ self.weights.to(source_map.dtype)


def _word_tokens(token_words: torch.Tensor, mask: torch.Tensor) -> tuple[dict[int, list[int]], list[int]]:
    """Token positions of each word, and the positions of special (non-word) tokens."""
    words: dict[int, list[int]] = {}
    special = []
    # as lists: on a GPU, reading tensors element by element would sync once per token
    for k, (w, real) in enumerate(zip(token_words.tolist(), mask.tolist())):
        if not real:
            continue
        if w >= 0:
            words.setdefault(w, []).append(k)
        else:
            special.append(k)
    return words, special


def align_words(source: list[str], target: list[str], mode: str) -> list[int]:
    """For each target word, the index of the source word it corresponds to, or -1.

    swap: words are paired by position (the prompts must have the same number of
    words); refine: a longest-matching-blocks diff, so words after an insertion keep
    pointing at their own source word.
    """
    if mode == "swap":
        if len(source) != len(target):
            raise ValueError(f"word swap needs prompts with the same number of words: {len(source)} "
                             f"({' '.join(source)!r}) vs {len(target)} ({' '.join(target)!r}); "
                             "use refine to add words")
        return list(range(len(target)))
    if mode == "refine":
        out = [-1] * len(target)
        matcher = difflib.SequenceMatcher(a=source, b=target, autojunk=False)
        for block in matcher.get_matching_blocks():
            for k in range(block.size):
                out[block.b + k] = block.a + k
        return out
    if mode == "same":
        if source != target:
            raise ValueError("this edit keeps the prompt; give no target prompt (or the same one)")
        return list(range(len(target)))
    raise ValueError(f"unknown alignment mode {mode!r}")


def align_tokens(text, source_row: int, target_row: int, mode: str) -> TokenAlignment:
    """Build the token alignment for rows of a batched TextFeatures."""
    L = text.tokens.shape[1]
    src_words, tgt_words = text.words[source_row], text.words[target_row]
    word_map = align_words(src_words, tgt_words, mode)
    s_tok, s_special = _word_tokens(text.token_words[source_row], text.mask[source_row])
    t_tok, t_special = _word_tokens(text.token_words[target_row], text.mask[target_row])
    W = torch.zeros(L, L)
    inserted = torch.zeros(L, dtype=torch.bool)
    replaced = torch.zeros(L, dtype=torch.bool)
    # Special tokens (start, end, punctuation) correspond in order: first to first, last to last.
    if s_special and t_special:
        pairs = [(s_special[0], t_special[0]), (s_special[-1], t_special[-1])]
        for a, b in pairs:
            W[a, b] = 1.0
        for b in t_special[1:-1]:
            inserted[b] = True
    for tw, sw in enumerate(word_map):
        targets = t_tok.get(tw, [])
        if sw < 0 or sw not in s_tok:
            inserted[targets] = True
            continue
        sources = s_tok[sw]
        if src_words[sw] != tgt_words[tw]:
            replaced[targets] = True
        if len(sources) == len(targets):
            for a, b in zip(sources, targets):
                W[a, b] = 1.0
        else:
            # A word split into a different number of sub-word tokens: every target token
            # takes the mean map of the source word's tokens.
            for b in targets:
                W[sources, b] = 1.0 / len(sources)
    device = text.tokens.device       # built once where the attention maps it is applied to live
    return TokenAlignment(W.to(device), inserted.to(device), replaced.to(device), list(src_words), list(tgt_words),
                          word_map)
