"""Natural-language captions for labelled mocap clips, and left/right swapping of text.

Captions are generated from a clip's content and style labels with varied subjects,
verb phrases and manner phrases, drawn reproducibly from the clip's name. What each
content label means was checked on the data itself (which wrist moves, where the root
goes): e.g. Bandai's "bye" waves the right hand, "walk-left" walks diagonally forward
to the left while still facing forward.
"""
from __future__ import annotations

import hashlib
import random
import re

SUBJECTS = ("a person", "someone", "a man", "a woman", "the person", "a character", "a figure", "somebody", "a guy",
            "a lady", "the man", "the woman")

# Verb phrases in the third person; {poss} becomes "their"/"his"/"her" to agree with the subject.
CONTENT_PHRASES: dict[str, tuple[str, ...]] = {
    "walk": ("walks forward", "walks straight ahead", "is walking forward", "takes a few steps forward",
             "walks ahead in a straight line", "strolls along", "goes forward on foot", "paces forward",
             "moves forward at a walk", "wanders straight on", "ambles forward", "saunters ahead",
             "strolls straight ahead", "treads forward", "walks along a straight path", "heads forward at a walk",
             "walks a few paces ahead", "is out for a walk", "walks on", "steps forward one foot after the other"),
    "run": ("runs forward", "jogs forward", "is running straight ahead", "runs ahead", "jogs along",
            "runs straight on", "goes for a jog", "moves forward at a run", "is jogging", "trots forward",
            "runs at an even pace", "jogs straight ahead", "lopes along", "runs along a straight line",
            "is out for a run", "runs forward at a jog"),
    "dash": ("sprints forward", "dashes ahead at full speed", "runs forward very fast", "sprints straight ahead",
             "rushes forward as quickly as possible", "breaks into a sprint", "runs flat out", "races forward",
             "bolts ahead", "charges forward at top speed", "runs at full tilt", "hurtles forward",
             "sprints as fast as possible", "speeds forward in a sprint"),
    "walk-back": ("walks backwards", "steps backward", "is walking backwards", "walks back without turning around",
                  "moves backwards", "backs away", "takes steps in reverse", "retreats backwards",
                  "backs up", "walks in reverse", "steps back several times", "reverses on foot"),
    "walk-left": ("walks diagonally forward to the left", "walks forward while drifting to the left",
                  "walks ahead and to the left, still facing forward", "walks forward at an angle to the left",
                  "sidles forward and to the left", "veers left while walking forward",
                  "walks forward, bearing to the left", "walks on a diagonal to the left",
                  "drifts leftwards as they walk forward"),
    "walk-right": ("walks diagonally forward to the right", "walks forward while drifting to the right",
                   "walks ahead and to the right, still facing forward", "walks forward at an angle to the right",
                   "sidles forward and to the right", "veers right while walking forward",
                   "walks forward, bearing to the right", "walks on a diagonal to the right",
                   "drifts rightwards as they walk forward"),
    "walk-turn-left": ("walks and turns left", "walks forward, then turns to the left", "walks in a left turn",
                       "turns left while walking", "walks around a corner to the left", "changes direction to the left",
                       "walks and curves to the left", "takes a left turn on foot", "walks and wheels around to the left",
                       "walks forward and bends the path to the left"),
    "walk-turn-right": ("walks and turns right", "walks forward, then turns to the right", "walks in a right turn",
                        "turns right while walking", "walks around a corner to the right",
                        "changes direction to the right", "walks and curves to the right",
                        "takes a right turn on foot", "walks and wheels around to the right",
                        "walks forward and bends the path to the right"),
    "bow": ("bows", "takes a bow", "bends forward in a bow", "bows politely", "bows deeply", "bows {poss} head and body",
            "leans the upper body forward in a bow", "bends at the waist", "bows in greeting",
            "makes a respectful bow", "bows low", "bends the torso forward to bow"),
    "bye": ("waves goodbye with {poss} right hand", "waves {poss} right hand to say goodbye",
            "says goodbye, waving the right hand", "waves the right hand in farewell", "says bye with the right hand",
            "bids farewell with the right hand", "waves farewell with the right hand",
            "waves the right hand while saying goodbye", "says goodbye with a wave of the right hand",
            "waves so long with the right hand"),
    "byebye": ("waves goodbye with both hands", "waves both hands to say goodbye", "says bye-bye with both hands",
               "waves both hands in farewell", "says farewell with both hands", "waves goodbye with both arms raised",
               "says goodbye, waving both hands", "waves farewell with both arms"),
    "guide": ("gestures with {poss} right hand to show the way", "guides someone with a sweep of the right arm",
              "points the way with {poss} right hand", "shows someone the direction with the right hand",
              "motions with the right arm to lead someone on", "directs someone with the right hand",
              "indicates the way with a sweep of the right hand", "ushers someone along with the right arm",
              "waves someone through with the right hand"),
    "respond": ("raises {poss} left hand to respond", "answers a call by lifting the left hand",
                "responds by raising the left hand", "puts up the left hand in reply",
                "replies by lifting the left hand", "acknowledges someone with a raised left hand",
                "answers by putting the left hand up", "lifts the left hand in answer"),
    "call": ("calls out to someone with both hands raised", "calls to somebody, lifting both hands",
             "shouts to get someone's attention, raising both hands", "cups both hands and calls out",
             "yells to someone with both arms up", "shouts out, holding both hands up",
             "hails someone with both hands raised", "calls for attention with both hands lifted"),
    "punch": ("throws punches", "punches forward", "is punching in the air", "boxes, throwing several punches",
              "strikes with the fists", "shadowboxes", "jabs with the fists", "throws a flurry of punches",
              "hits out with both fists", "punches again and again", "throws jabs and hooks"),
    "kick": ("kicks", "does a series of kicks", "kicks into the air", "performs kicks", "kicks out with a leg",
             "kicks high several times", "swings a leg up in a kick", "kicks with one leg",
             "throws a high kick", "kicks the air repeatedly", "delivers a few kicks", "lifts a leg and kicks"),
    "slash": ("slashes with an imaginary sword", "swings {poss} arms as if slashing with a blade",
              "makes slashing motions with {poss} arms", "fights with a pretend sword",
              "slices the air as if holding a katana", "swings a pretend sword", "cuts the air with a sword",
              "slashes as if wielding a blade", "sword-fights an invisible enemy"),
    "dance-short": ("dances", "performs a dance", "is dancing energetically", "does a dance routine",
                    "dances to music", "does a few dance moves", "dances to the beat", "moves to the music",
                    "grooves along", "dances rhythmically", "bops to a rhythm", "busts a few moves"),
    "dance-long": ("dances", "performs a long dance", "is dancing", "does a dance routine", "dances to the beat",
                   "moves to the music", "dances rhythmically"),
    "wave-left-hand": ("waves {poss} left hand", "waves with the left hand", "raises {poss} left hand and waves",
                       "waves hello with {poss} left hand", "waves the left arm", "gives a wave with the left hand",
                       "greets someone with a wave of the left hand", "waves hi with the left hand",
                       "waves the left hand back and forth", "waves a greeting with the left hand"),
    "wave-right-hand": ("waves {poss} right hand", "waves with the right hand", "raises {poss} right hand and waves",
                        "waves hello with {poss} right hand", "waves the right arm",
                        "gives a wave with the right hand", "greets someone with a wave of the right hand",
                        "waves hi with the right hand", "waves the right hand back and forth",
                        "waves a greeting with the right hand"),
    "wave-both-hands": ("waves both hands", "waves with both arms", "raises both hands and waves",
                        "waves both arms above {poss} head", "waves with two hands", "waves both hands overhead",
                        "greets someone by waving both arms", "waves hello with both hands",
                        "waves both hands back and forth"),
    "raise-up-left-hand": ("raises {poss} left hand", "lifts the left hand up", "puts {poss} left arm up in the air",
                           "raises the left arm", "holds the left hand up high", "reaches up with the left hand",
                           "puts the left hand up", "lifts the left arm over {poss} head", "sticks the left arm up",
                           "raises the left hand above {poss} head"),
    "raise-up-right-hand": ("raises {poss} right hand", "lifts the right hand up",
                            "puts {poss} right arm up in the air", "raises the right arm", "holds the right hand up high",
                            "reaches up with the right hand", "puts the right hand up",
                            "lifts the right arm over {poss} head", "sticks the right arm up",
                            "raises the right hand above {poss} head"),
    "raise-up-both-hands": ("raises both hands", "lifts both arms up", "puts both hands up in the air",
                            "raises both arms over {poss} head", "holds both hands up high", "reaches up with both hands",
                            "throws both hands up", "lifts both hands overhead", "puts both arms up",
                            "lifts both hands high above {poss} head"),
}

# Manner: (adverbial phrases, adjectives for the subject). An empty adverb means "no style word".
# Speed words go to the styles whose clips move at that speed (slowly: old, elderly, tired; quickly: active).
STYLE_PHRASES: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "normal": (("", "normally", "in an ordinary way", "casually", "calmly", "in a relaxed way"),
               ("",)),
    "happy": (("happily", "cheerfully", "in a happy mood", "joyfully", "gladly", "merrily", "gleefully",
               "with a smile", "in high spirits"), ("happy", "cheerful", "joyful", "glad")),
    "sad": (("sadly", "in a sad way", "gloomily", "looking sad", "unhappily", "dejectedly", "sorrowfully",
             "mournfully", "with a heavy heart", "downheartedly"), ("sad", "gloomy", "unhappy", "sorrowful")),
    "angry": (("angrily", "in an angry way", "furiously", "looking angry", "aggressively", "irritably", "in a rage",
               "crossly", "with fury"), ("angry", "furious", "mad", "irritated")),
    "proud": (("proudly", "with pride", "in a proud manner", "with the head held high", "confidently",
               "haughtily"), ("proud", "confident")),
    "not-confident": (("timidly", "without confidence", "hesitantly", "shyly", "nervously", "uncertainly",
                       "meekly", "insecurely"), ("timid", "hesitant", "shy", "nervous", "insecure")),
    "masculinity": (("in a masculine way", "with a masculine manner", "in a manly way", "like a tough guy"),
                    ("masculine", "manly")),
    "masculine": (("in a masculine way", "with a masculine manner", "in a manly way", "like a tough guy"),
                  ("masculine", "manly")),
    "feminine": (("in a feminine way", "with a feminine manner", "gracefully, in a feminine style", "daintily",
                  "elegantly"), ("feminine", "graceful")),
    "childish": (("like a child", "in a childish way", "playfully like a kid", "playfully", "like a little kid"),
                 ("childish", "childlike", "playful")),
    "old": (("like an old person", "slowly like an elderly person", "in an old, frail way", "slowly", "stiffly",
             "feebly", "at a slow pace", "like an old man", "like an old woman"), ("old", "elderly", "frail")),
    "elderly": (("like an elderly person", "like an old person", "slowly and carefully like the elderly", "slowly",
                 "carefully", "unsteadily", "feebly", "at a slow pace", "like an old man", "like an old woman",
                 "shuffling like a senior"), ("elderly", "old", "aged", "frail")),
    "tired": (("tiredly", "wearily", "looking tired", "in a tired way", "sluggishly", "dragging {poss} feet",
               "drowsily", "lethargically", "slowly and tiredly", "with heavy steps"),
              ("tired", "weary", "sleepy", "fatigued")),
    "exhausted": (("looking exhausted", "wearily", "in an exhausted way", "as if completely worn out", "heavily",
                   "sluggishly", "out of breath", "worn out", "with no energy left", "utterly drained",
                   "with heavy steps", "dragging {poss} feet"), ("exhausted", "worn-out", "drained", "fatigued")),
    "active": (("energetically", "actively", "full of energy", "vigorously", "quickly", "with lots of pep",
                "briskly", "dynamically", "with vigor", "in a lively way", "at a quick pace", "fast"),
               ("energetic", "active", "lively", "brisk")),
    "youthful": (("youthfully", "in a youthful way", "with youthful energy", "lightly and briskly", "briskly",
                  "with a spring in the step", "with a bounce", "sprightly"), ("youthful", "young", "sprightly")),
    "musical": (("theatrically, like in a musical", "in a showy, musical style", "like a stage performer",
                 "theatrically", "with showy flair"), ("theatrical", "showy")),
    "giant": (("like a giant", "with heavy, giant-like movements", "like a huge, heavy giant", "lumberingly",
               "ponderously"), ("giant", "hulking")),
    "chimpira": (("like a thug", "with a swaggering, thuggish attitude", "like a street punk", "with a swagger",
                  "like a gangster"), ("swaggering", "thuggish")),
}

_POSSESSIVE = {"a man": "his", "a woman": "her", "a guy": "his", "a lady": "her", "the man": "his",
               "the woman": "her"}


def _article(word: str) -> str:
    return "an" if word[:1] in "aeiou" else "a"


def caption_variants(content: str, style: str, plain: bool = False) -> list[tuple[str, int]]:
    """Every caption the templates can produce for a (content, style) pair, each with
    the index of the verb phrase it uses; plain: only those that name no manner."""
    if content not in CONTENT_PHRASES:
        raise KeyError(f"no caption templates for content {content!r}")
    if style not in STYLE_PHRASES:
        raise KeyError(f"no caption templates for style {style!r}")
    adverbs, adjectives = (("",), ("",)) if plain else STYLE_PHRASES[style]
    out = []
    for subj in SUBJECTS:
        poss = _POSSESSIVE.get(subj, "their")
        for k, verb in enumerate(CONTENT_PHRASES[content]):
            v = verb.format(poss=poss)
            for adv in adverbs:
                adv = adv.format(poss=poss)
                if not adv:
                    out.append((f"{subj} {v}", k))
                    out.append((f"{subj} {v} and then stops", k))
                    continue
                out.append((f"{subj} {v} {adv}", k))
                # word order varies in what people type: "a man wearily walks forward"
                if " " not in adv and adv.endswith("ly"):
                    out.append((f"{subj} {adv} {v}", k))
            for adj in adjectives:
                if adj and subj.startswith("a "):
                    out.append((f"{_article(adj)} {adj} {subj[2:]} {v}", k))
    return out


def captions_for(content: str, style: str, key: str, n: int = 3, plain: bool = False) -> list[str]:
    """`n` distinct captions for a clip, the same for the same key on every run (plain: naming no manner)."""
    variants = caption_variants(content, style, plain)
    seed = int.from_bytes(hashlib.sha256(key.encode()).digest()[:8], "little")
    rng = random.Random(seed)
    rng.shuffle(variants)
    picked: list[str] = []
    # Prefer captions that differ in their verb phrase, so the set is genuinely varied.
    used = set()
    for text, verb in variants:
        if verb not in used:
            used.add(verb)
            picked.append(text)
        if len(picked) == n:
            return picked
    for text, _ in variants:
        if len(picked) == n:
            break
        if text not in picked:
            picked.append(text)
    return picked


_ARTICLES = frozenset(("a", "an", "the"))


def crossover(first: str, second: str, rng) -> str:
    """`first` up to a word it shares with `second`, then `second` from that word on: a wording that
    neither has, e.g. "a man kicks with one leg" x "a guy waves with his right hand" -> "a man kicks
    with his right hand". Neither caption's first word, nor an article, is a cut, nor one that gives
    back either caption; with none left, `first` as it is. rng: a numpy Generator (which wording)."""
    a, b = first.split(), second.split()
    made = {" ".join(a[:i] + b[j:]) for i, w in enumerate(a[1:], 1) if w.lower() not in _ARTICLES
            for j, v in enumerate(b[1:], 1) if v.lower() == w.lower()} - {first, second}
    return sorted(made)[int(rng.integers(len(made)))] if made else first


_SWAPS = (("counterclockwise", "clockwise"), ("counter-clockwise", "clockwise"), ("left", "right"))


def swap_left_right(text: str) -> str:
    """Swap left/right (and clockwise/counterclockwise) words, keeping case, e.g. for
    captions of mirrored motions."""
    pairs = {}
    for a, b in _SWAPS:
        pairs.setdefault(a, b)
        pairs.setdefault(b, a)
    pattern = re.compile(r"\b(" + "|".join(sorted(map(re.escape, pairs), key=len, reverse=True)) + r")\b",
                         re.IGNORECASE)

    def repl(m: re.Match) -> str:
        w = m.group(0)
        r = pairs[w.lower()]
        return r.capitalize() if w[0].isupper() else r

    return pattern.sub(repl, text)


MIRRORED_CONTENT = {"walk-left": "walk-right", "walk-right": "walk-left",
                    "walk-turn-left": "walk-turn-right", "walk-turn-right": "walk-turn-left",
                    "wave-left-hand": "wave-right-hand", "wave-right-hand": "wave-left-hand",
                    "raise-up-left-hand": "raise-up-right-hand", "raise-up-right-hand": "raise-up-left-hand"}


# A small part-of-speech lexicon for the template vocabulary, so caption lines carry
# HumanML3D's `word/POS` token field without a tagger dependency.
_POS = {
    "a": "DET", "an": "DET", "the": "DET", "both": "DET", "their": "DET", "his": "DET", "her": "DET",
    "someone": "PRON", "somebody": "PRON", "someone's": "PRON",
    "and": "CCONJ", "then": "ADV", "while": "SCONJ", "as": "SCONJ", "if": "SCONJ", "like": "ADP",
    "with": "ADP", "in": "ADP", "to": "ADP", "into": "ADP", "over": "ADP", "above": "ADP", "without": "ADP",
    "at": "ADP", "of": "ADP", "by": "ADP", "up": "ADP", "out": "ADP",
}
_LEMMA = {"walks": "walk", "runs": "run", "jogs": "jog", "sprints": "sprint", "dashes": "dash", "steps": "step",
          "takes": "take", "bows": "bow", "bends": "bend", "waves": "wave", "raises": "raise", "lifts": "lift",
          "puts": "put", "turns": "turn", "says": "say", "gestures": "gesture", "guides": "guide",
          "points": "point", "answers": "answer", "responds": "respond", "calls": "call", "shouts": "shout",
          "throws": "throw", "punches": "punch", "boxes": "box", "kicks": "kick", "does": "do",
          "performs": "perform", "slashes": "slash", "swings": "swing", "makes": "make", "dances": "dance",
          "is": "be", "hands": "hand", "arms": "arm", "steps,": "step", "punches,": "punch", "ambles": "amble",
          "saunters": "saunter", "strolls": "stroll", "treads": "tread", "heads": "head", "trots": "trot",
          "lopes": "lope", "races": "race", "bolts": "bolt", "charges": "charge", "hurtles": "hurtle",
          "speeds": "speed", "retreats": "retreat", "backs": "back", "reverses": "reverse", "veers": "veer",
          "drifts": "drift", "curves": "curve", "wheels": "wheel", "bids": "bid", "directs": "direct",
          "ushers": "usher", "indicates": "indicate", "replies": "reply", "acknowledges": "acknowledge",
          "yells": "yell", "hails": "hail", "jabs": "jab", "hits": "hit", "delivers": "deliver", "cuts": "cut",
          "grooves": "groove", "bops": "bop", "busts": "bust", "greets": "greet", "sticks": "stick",
          "stretches": "stretch", "holds": "hold", "stops": "stop", "moves": "move", "goes": "go"}


def tag_tokens(caption: str) -> str:
    words = re.findall(r"[A-Za-z'-]+", caption.lower())
    tags = []
    for w in words:
        lemma = _LEMMA.get(w, w)
        if w in _POS:
            pos = _POS[w]
        elif w in _LEMMA and lemma not in ("hand", "arm"):
            pos = "VERB"
        elif w.endswith("ly"):
            pos = "ADV"
        elif w in ("left", "right", "forward", "backward", "backwards", "ahead", "back", "straight", "diagonally"):
            pos = "ADV"
        else:
            pos = "NOUN"
        tags.append(f"{lemma}/{pos}")
    return " ".join(tags)


def caption_line(caption: str, start: float = 0.0, end: float = 0.0) -> str:
    """One line of a HumanML3D texts/<id>.txt file."""
    return f"{caption}#{tag_tokens(caption)}#{start:.1f}#{end:.1f}"
