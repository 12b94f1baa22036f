"""``python -m crs_study`` runs the command line."""

import sys

from crs_study.cli import main

sys.exit(main())
