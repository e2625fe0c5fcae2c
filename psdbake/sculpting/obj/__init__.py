"""The sculptor's loop through Wavefront OBJ (``pose --obj-dir``, ``sculpts``).

Every sculpting application (ZBrush, Mudbox, Blender, Maya) reads and writes OBJ with the
vertex order kept, which is all psdbake needs to put a sculpt back on its mesh. These
modules are plain Python and numpy: ``usd/meshfaces.py`` reads what they need from USD.
"""
