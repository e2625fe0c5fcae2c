"""``psdbake mirror``: one side's correctives groups made into the other side's.

``symmetry`` the joint map, the mirror plane, partner joints and vertices
``poses``    a group's pose space reflected and its RBF refitted over the mirrored centres
``groups``   every group mirrored: partners, poses, offsets, client-safe channels
"""
