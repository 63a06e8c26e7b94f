"""`bridge-bench`: see `bridge_jax.bench.cli`."""
import sys

from bridge_jax.bench.cli import main

sys.exit(main())
