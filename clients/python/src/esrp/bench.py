"""`python -m esrp.bench`: the benchmark of the Python client, the same program as `esrp bench`.

The program is `esrp.cli.bench` (its docstring says what it measures); this entry point runs its
`main` and keeps its public names importable as `esrp.bench.main`, `esrp.bench.run`, ...
"""

from __future__ import annotations

import sys

from .cli.bench import SCENARIOS, Measurement, main, run

__all__ = ["SCENARIOS", "Measurement", "main", "run"]

if __name__ == "__main__":
    sys.exit(main())
