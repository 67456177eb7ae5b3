"""``python -m bonesim.cli``: the command line."""
import sys

from bonesim.cli.main import main

__all__ = []

if __name__ == "__main__":
    sys.exit(main())
