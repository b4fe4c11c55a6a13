"""ISAC Twin Blender add-on: room modelling, radio materials, devices and scene export.

Register/unregister only; the logic lives in plain modules that operators,
panels, ``bpy`` scripts and tests share.
"""

bl_info = {
    "name": "ISAC Twin",
    "author": "ISAC Twin developers",
    "version": (0, 1, 0),
    "blender": (4, 2, 0),
    "location": "View3D > Sidebar > ISAC Twin",
    "description": "Digital twin for integrated sensing, communications and robotics",
    "category": "Import-Export",
}

from . import operators, panels, properties  # noqa: E402

_MODULES = (properties, operators, panels)


def register() -> None:
    for module in _MODULES:
        module.register()


def unregister() -> None:
    for module in reversed(_MODULES):
        module.unregister()
