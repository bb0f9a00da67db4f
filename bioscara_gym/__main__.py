"""``python -m bioscara_gym``: the ``bioscara`` command."""

import sys

from bioscara_gym.cli import main

sys.exit(main())
