"""The sculptor's loop: ``pose --obj-dir`` writes an OBJ per mesh and pose, ``sculpts`` reads the
edited ones back. ``loop`` is the orchestration, ``obj`` the file format."""
