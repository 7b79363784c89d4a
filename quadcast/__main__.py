"""``python -m quadcast``: the command line."""
import sys

from quadcast.cli import main

sys.exit(main())
