"""eval over a shot: which frames, each animation's corrective weights per frame, and the posed points.

``frames``     --frames checked against the animation's authored samples, or its own samples
``evaluation`` the weights of every corrected mesh's groups on the SkelAnimation that poses it
"""
