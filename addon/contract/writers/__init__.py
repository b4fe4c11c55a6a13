# SPDX-License-Identifier: Apache-2.0
"""Scene-folder writers (``docs/config.md``): float formatting (:mod:`.numbers`), PLY
meshes (:mod:`.geometry`), the Mitsuba XML scene (:mod:`.mitsuba_xml`) and
``twin.toml`` (:mod:`.twin_toml`). Standard library only: the add-on's exporter calls
them with what it reads from Blender, the engine's synthetic rooms with numbers."""
