"""twin stage: the twin folder and its exports.

`manifest` (twin.json), `build` (build_twin: geometry + files + exporters; export_twin), `urdf`, `moveit`
(.scene text + CollisionObject YAML), `gltf` (GLB), `splats` (per-object splat PLYs in the object frame),
`mjcf` (MuJoCo). Imports stay lazy: `splattwin.twin.manifest` is imported by every stage.
"""
