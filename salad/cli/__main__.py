"""`python -m salad.cli`, as torchrun starts the data-parallel training."""
from . import run

run()
