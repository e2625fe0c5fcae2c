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
