"""The product for clients that are not UsdSkel: ``gltf`` (export-gltf, game engines) and
``blender`` (export-blender, a live rig whose drivers compute the psd: weights)."""
