"""``python -m bonesim``: the command line (:mod:`bonesim.cli.main`)."""
import sys

from bonesim.cli.main import main

__all__ = []

if __name__ == "__main__":
    sys.exit(main())
