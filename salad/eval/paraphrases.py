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
