"""``python -m bonesim``: the command line (:mod:`bonesim.cli`)."""
import sys

from .cli import main

__all__ = []

if __name__ == "__main__":
    sys.exit(main())
