"""`python -m salad.cli`, as torchrun starts the data-parallel training."""
import sys

from . import main

sys.exit(main())
