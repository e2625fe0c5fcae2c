"""The psd: model: what a corrective's weight is at a pose, in numpy and SciPy alone.

``posespace``   joint rotations -> pose coordinates (rotation vector, swing-twist, quaternion)
``quaternions`` the float64 quaternion arithmetic the formula is written in
``rbf``         the cardinal RBF: kernels, polynomial terms, the formula and its evaluation
``weights``     a group's weights at a pose: RBF, gates and combinations, options
``channels``    client-safe channels: each column split and scaled so written weights stay in [0, 1]
``data``        the psd: data classes (``DriverData``, ``BlendShapeData``), as read and written by ``usd/``
``rig``         the rig as the model sees it (``SkinnedMesh``, ``BindSpace``)

Nothing here imports USD: a program without usd-core can evaluate a CORRECTIVES layer's
weights from its psd: values (``weights``), and tests/test_layering.py holds that property.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from .channels import channel_names, channel_weights
from .data import DriverData
from .weights import column_weights_of_local

__all__ = ["DriverData", "evaluate_weights"]


def evaluate_weights(groups: Sequence[tuple[str, DriverData]], local: NDArray[np.float64], joints: Sequence[str]
                     ) -> dict[str, NDArray[np.float64]]:
    """Every corrective channel's weight, as ``psdbake eval`` writes it, from psd: values alone.

    groups: one mesh's correctives groups, (name, DriverData) as read from its ``psd:`` attributes
    (``psdbake.usd.schema.read_groups`` reads them; any reader of the documented schema will do);
    local: (f, J, 4, 4) every joint's local transform per frame (row-vector matrices, UsdSkel's
    ``ComputeJointLocalTransforms``), in skeleton order ``joints``.
    Returns channel name -> (f,) weights: pose coordinates, cardinal RBF, gates, options, and the
    client-safe channel scaling, in that order (the formula in the psd: reference).
    """
    b = column_weights_of_local(groups, np.asarray(local, dtype=np.float64), joints)
    out: dict[str, NDArray[np.float64]] = {}
    for name, data in groups:
        for channel, column in zip(channel_names(data), channel_weights(data, b[name]).T, strict=True):
            out[channel] = column
    return out
