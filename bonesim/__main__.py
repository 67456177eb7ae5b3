"""``python -m bonesim``: the command line (:mod:`bonesim.cli`)."""
import sys

from .cli import main

sys.exit(main())
