# SPDX-License-Identifier: Apache-2.0
"""The add-on contract: what the Blender add-on and the engine must agree on.

Standard library only (no ``bpy``, no numpy), Apache-2.0. The engine imports it as
``isac_twin.contract``; the Blender extension ships the same files as its
``contract`` subpackage (``addon/contract/`` is the one source of both).

* :mod:`.schema` -- the scene-folder vocabulary (patterns, polarizations, robot
  models and bodies, defaults; ``docs/config.md``).
* :mod:`.wire` -- the live link's wire format (framing, messages, edit and command
  ops; ``docs/wire.md``).
* :mod:`.writers` -- the scene-folder writers (PLY meshes, Mitsuba XML,
  ``twin.toml``) that the add-on's exporter and the engine's synthetic rooms share.
* :mod:`.errors` -- the root of the project's error hierarchy.

Only relative imports inside: the package works under either name.
"""
