"""twin stage: the twin folder and its exports.

`manifest` (twin.json), `build` (build_twin: geometry + files + exporters; export_twin), `urdf`, `moveit`
(.scene text + CollisionObject YAML), `gltf` (GLB), `splats` (per-object splat PLYs in the object frame),
`mjcf` (MuJoCo). Imports stay lazy: `splattwin.twin.manifest` is imported by every stage.
"""

from __future__ import annotations

from splattwin._lazy import lazy_exports

# Lazy: nothing is imported until a name is used (`splattwin --help` imports the options modules only).
_EXPORTS = {"build_twin": "build", "export_twin": "build", "check_objects": "build", "Manifest": "manifest",
            "ObjectEntry": "manifest", "ExportOptions": "options", "TwinOptions": "options", "add_scene_goal": "stage"}

__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
