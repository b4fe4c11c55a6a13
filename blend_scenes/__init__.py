"""The bundled rooms, as data: installed as ``isac_twin.scenes``.

Each folder holds a room's bpy build script, its ``.blend`` file and its exported
scene folder ``<room>/scene/``; only the scene folders (and each room's README)
ship in the wheel. Find them with :func:`isac_twin.scene.bundled.bundled_scene_dir`.
"""
