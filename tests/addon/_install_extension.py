"""Helper run in a fresh interpreter by test_extension.py: install the built zip, use it.

Usage: python _install_extension.py <zip> <repo dir>
Set BLENDER_USER_RESOURCES to a temporary folder first so no real user
preferences are touched. Prints one JSON object on the last stdout line.
"""

import json
import sys

import bpy

zip_path, repo_dir = sys.argv[1], sys.argv[2]
out = {}
prefs = bpy.context.preferences
prefs.extensions.repos.new(name="isac_test", module="isac_test", custom_directory=repo_dir)
out["install"] = sorted(bpy.ops.extensions.package_install_files(
    filepath=zip_path, repo="isac_test", enable_on_install=True))
out["enabled"] = "bl_ext.isac_test.isac_twin" in prefs.addons.keys()
out["operator_module"] = bpy.types.ISAC_OT_add_room.__module__
out["add_room"] = sorted(bpy.ops.isac.add_room(width=4.0, depth=3.0, height=2.5))
out["objects"] = sorted(o.name for o in bpy.data.objects if o.name.startswith("Room"))
print(json.dumps(out))
