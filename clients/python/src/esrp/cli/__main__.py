"""`python -m esrp.cli`: the `esrp` command."""

import sys

from . import main

sys.exit(main())
