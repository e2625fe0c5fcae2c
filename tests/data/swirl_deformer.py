"""A studio-style non-linear deformer for tests: a position-dependent twist and ripple."""

import numpy as np


def factory(stage, mesh_path, time):
    def deform(points):
        x, y, z = points.T
        ang = 0.3 * np.sin(0.7 * x)
        c, s = np.cos(ang), np.sin(ang)
        return np.stack([x + 0.04 * np.sin(2.0 * y), c * y - s * z, s * y + c * z], axis=1)

    return deform
