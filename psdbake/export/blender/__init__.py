"""The live Blender rig: the ``psd:`` weight formula compiled into Blender drivers.

``simple``   Blender's simple expressions: the expression tree, its text, and a Python
             evaluator with Blender's semantics (float32 between drivers), for tests.
``graph``    the driver graph: which quantities become driven properties, so that every
             expression fits Blender's 255 characters; and its evaluation.
``compiler`` one function per building block of the ``psd:`` formula (pose coordinates of a
             driver joint, squared distance, kernel, polynomial term, sum, gates, options,
             client-safe channel scaling), composed into one graph per mesh.
``export``   ``psdbake export-blender``: USD in, the plan handed to Blender, the .blend out.
``rig_script`` the script Blender runs (it imports ``bpy`` and nothing of psdbake).

Everything but ``export`` and ``rig_script`` is pure Python over the ``psd:`` data classes:
no USD stage and no Blender, so ``make test`` checks it.
"""
