"""`python -m occvo_cli ...`: the same as the `occvo` console script."""

import sys

from occvo_cli.cli import main

sys.exit(main())
