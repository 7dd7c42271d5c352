"""Held-out prompts for the fidelity benchmark: paraphrases of every trained action, written for the
benchmark and never used as training captions (a test checks that no caption template produces one).

Keys are content labels, or "content/style" for the styles that change a motion's speed.
"""
from __future__ import annotations

HELD_OUT: dict[str, tuple[str, ...]] = {
    "walk": ("someone strolls forward at an easy pace", "a person ambles ahead on foot"),
    "run": ("a person jogs quickly down the road", "somebody runs at a steady pace in a straight line"),
    "dash": ("a person bolts forward as fast as possible", "someone races ahead at top speed"),
    "walk-back": ("a person backs up step by step", "someone retreats by walking in reverse"),
    "walk-left": ("a person walks ahead while veering to the left", "someone steps forward and drifts leftwards"),
    "walk-right": ("a person walks ahead while veering to the right", "someone steps forward and drifts rightwards"),
    "walk-turn-left": ("a person walks and curves around to the left", "someone strolls forward and makes a left turn"),
    "walk-turn-right": ("a person walks and curves around to the right",
                        "someone strolls forward and makes a right turn"),
    "bow": ("a person bends at the waist to greet someone", "someone gives a polite bow"),
    "bye": ("a person says farewell with a wave of the right hand", "someone waves the right hand to part"),
    "byebye": ("a person waves goodbye using both arms", "someone bids farewell with both hands"),
    "guide": ("a person shows the way with a sweep of the right hand", "someone directs a visitor with the right arm"),
    "respond": ("a person answers by lifting the left hand", "someone replies with a raised left hand"),
    "call": ("a person lifts both hands and calls out", "someone shouts for attention with both arms up"),
    "punch": ("a person punches the air again and again", "someone throws a series of jabs"),
    "kick": ("a man kicks with his right leg", "someone delivers a high kick"),
    "slash": ("a person swings an invisible sword", "someone cuts through the air with a blade"),
    "dance-short": ("someone grooves to the music", "a person moves rhythmically to a beat"),
    "wave-left-hand": ("a person greets someone by waving the left hand", "someone waves hi with the left arm"),
    "wave-right-hand": ("a person greets someone by waving the right hand", "someone waves hi with the right arm"),
    "wave-both-hands": ("a person waves with both arms overhead", "someone greets people by waving both hands"),
    "raise-up-left-hand": ("a person puts up the left hand", "someone lifts the left arm overhead"),
    "raise-up-right-hand": ("a person puts up the right hand", "someone lifts the right arm overhead"),
    "raise-up-both-hands": ("a person lifts both arms into the air", "someone puts both hands high up"),
    "walk/exhausted": ("someone walks forward completely worn out", "a person trudges ahead, totally exhausted"),
    "walk/elderly": ("an old man shuffles forward", "a person walks ahead like a frail old man"),
    "walk/active": ("a person walks forward briskly and full of energy", "someone marches ahead with lots of energy"),
}

# A second set, written later and kept apart the same way, to tell whether a change to the caption templates
# helps paraphrase in general or only the first set's wording. `salad eval-fidelity --prompt-set b`.
HELD_OUT_B: dict[str, tuple[str, ...]] = {
    "walk": ("a person makes their way forward on foot", "a woman goes for a short walk straight ahead"),
    "run": ("a runner moves forward at a comfortable jog", "a man runs ahead without hurrying"),
    "dash": ("a person runs as fast as they can", "an athlete sprints flat out down a track"),
    "walk-back": ("a man steps backwards a few times", "a person moves back while still facing forward"),
    "walk-left": ("a woman walks forward on a slant to the left", "a person heads forward and a bit to the left"),
    "walk-right": ("a woman walks forward on a slant to the right", "a person heads forward and a bit to the right"),
    "walk-turn-left": ("a person walks and swings around to their left", "a man walking forward turns left"),
    "walk-turn-right": ("a person walks and swings around to their right", "a man walking forward turns right"),
    "bow": ("a man bows down respectfully", "a person lowers the upper body in a deep bow"),
    "bye": ("a man waves his right hand as he leaves", "a person bids goodbye with the right hand"),
    "byebye": ("a woman waves goodbye with both of her hands", "a person says goodbye waving two hands"),
    "guide": ("a person points out the way with the right arm", "a man shows someone where to go with his right hand"),
    "respond": ("a person lifts the left hand to answer", "a woman puts her left hand up in response"),
    "call": ("a person raises both arms and shouts to someone", "a man calls out loudly with both hands up"),
    "punch": ("a boxer punches forward several times", "a person hits the air with the fists"),
    "kick": ("a person kicks a leg up high", "a fighter does a few kicks"),
    "slash": ("a person slashes the air with a sword", "a samurai swings a katana"),
    "dance-short": ("a woman dances around happily", "a person does a little dance"),
    "wave-left-hand": ("a woman waves with her left hand", "a man lifts his left hand and waves it"),
    "wave-right-hand": ("a woman waves with her right hand", "a man lifts his right hand and waves it"),
    "wave-both-hands": ("a person waves both arms in the air", "a man waves with both of his hands"),
    "raise-up-left-hand": ("a woman raises her left arm", "a person sticks the left hand up"),
    "raise-up-right-hand": ("a woman raises her right arm", "a person sticks the right hand up"),
    "raise-up-both-hands": ("a person throws both arms up", "a man raises both of his arms"),
    "walk/exhausted": ("a man walks forward, drained and out of energy", "an exhausted woman walks ahead"),
    "walk/elderly": ("an elderly woman walks forward slowly", "a person walks ahead like an old man"),
    "walk/active": ("a person walks forward with a lively step", "a man walks ahead vigorously"),
}

PROMPT_SETS: dict[str, dict[str, tuple[str, ...]]] = {"a": HELD_OUT, "b": HELD_OUT_B}
