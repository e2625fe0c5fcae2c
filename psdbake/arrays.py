"""Array aliases shared by the pipeline, with their shapes (numpy float64 unless said)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Points = NDArray[np.float64]  # (n, 3) positions or offsets, mesh local space
Matrices = NDArray[np.float64]  # (j, 4, 4) Gf row-vector transforms (p' = p . M)
Quaternions = NDArray[np.float64]  # (j, 4) scalar-last (x, y, z, w), as scipy
