"""Example prompts in the words the embedded model was trained on: Bandai-Namco's motions
(walk, run, turns, waves, raises, bow, bye, punch, kick, dance) and their styles."""

EXAMPLE_PROMPTS = (
    "a person waves their right hand happily",
    "an exhausted person walks forward",
    "someone walks and turns left",
    "a woman waves goodbye with her right hand",
    "an angry man throws punches",
    "a person raises both hands proudly",
    "an elderly person walks and turns right",
    "someone bows politely",
    "a person kicks into the air energetically",
    "a man runs forward like a giant",
    "a person dances cheerfully",
    "a sad person waves their left hand",
    "a timid person raises their left hand",
    "someone walks forward like a thug",
    "a person waves both hands like a child",
    "a tired woman walks forward in a feminine way",
)
