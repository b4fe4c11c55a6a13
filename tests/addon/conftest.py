"""Fixtures for the add-on tests: the real ``bpy`` module, headless, with the add-on registered.

The add-on is registered once per session as a legacy add-on (``import addon``);
each test gets an emptied scene with default ISAC settings.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

bpy = pytest.importorskip("bpy")


@pytest.fixture(scope="session")
def addon_module():
    """The add-on package, registered for the whole session."""
    import addon

    if not hasattr(bpy.types.Scene, "isac"):
        addon.register()
    yield addon
    if hasattr(bpy.types.Scene, "isac"):
        addon.unregister()


def empty_scene():
    """Remove every object, mesh and collection; reset the scene's ISAC settings."""
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    for mesh in list(bpy.data.meshes):
        bpy.data.meshes.remove(mesh)
    for coll in list(bpy.data.collections):
        bpy.data.collections.remove(coll)
    scene = bpy.context.scene
    scene.name = "Scene"
    props = scene.isac
    props.links.clear()
    props.radio_materials.clear()
    for key in props.bl_rna.properties.keys():
        if key not in ("rna_type", "links", "name"):
            props.property_unset(key)
    return scene


@pytest.fixture(scope="session")
def reset_scene(addon_module):
    """The :func:`empty_scene` function, for fixtures with a wider scope."""
    return empty_scene


@pytest.fixture
def scene(addon_module):
    """The context scene, emptied, with default radio settings."""
    return empty_scene()


class LayoutStub:
    """Stands in for ``UILayout``: records what a panel's draw() asks for.

    ``calls`` is shared by all sub-layouts: tuples like ("prop", "frequency_hz"),
    ("operator", "isac.export_scene"), ("label", text, icon), ("template_list", name).
    """

    def __init__(self, calls=None):
        self.calls = [] if calls is None else calls

    def _child(self, *args, **kwargs):
        return LayoutStub(self.calls)

    row = column = box = split = column_flow = grid_flow = _child

    def prop(self, data, prop, **kwargs):
        self.calls.append(("prop", prop))

    def prop_search(self, data, prop, search_data, search_prop, **kwargs):
        self.calls.append(("prop", prop))

    def operator(self, idname, **kwargs):
        self.calls.append(("operator", idname))

        class _Props:  # operator() returns settable properties
            pass

        return _Props()

    def label(self, text="", icon="NONE", **kwargs):
        self.calls.append(("label", text, icon))

    def separator(self, **kwargs):
        pass

    def template_list(self, listtype, list_id, data, propname, active_data, active_prop, **kw):
        self.calls.append(("template_list", listtype, propname))


@pytest.fixture
def layout_stub():
    return LayoutStub()
