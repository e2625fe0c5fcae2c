"""The black-box inverse: rest-space offsets that skinning (and any deformer chain) maps onto a sculpt.

``powell``      Powell's method in lockstep over many small independent problems (one per vertex)
``inverse``     one example's per-vertex inverse: which vertices, the solve, the residual report
``coupled``     the joint inverse when a deformer couples vertices (Delta Mush): smooth start, Newton-Krylov
``smoothstart`` the coupled inverse's smooth start: the chain's smoothing measured, Levenberg-Marquardt over smooth fields
``smoothbasis`` the mesh's smoothest fields, sized to a region, for the smooth start
``solve``       every example's inverse, serially or in worker processes, through the black box

The solver only calls the black box (``usd/blackbox.py``): it never looks inside the skinning.
"""
