"""``make bench``: ratios against the reference methods, each benchmark a module run with ``python -m``."""

import psdbake  # noqa: F401  (first: psdbake.reproducible pins the BLAS kernel before numpy loads)
