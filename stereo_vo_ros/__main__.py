"""``python -m stereo_vo_ros`` runs the ``stereo_vo`` command line."""

import sys

from .cli import main

sys.exit(main())
