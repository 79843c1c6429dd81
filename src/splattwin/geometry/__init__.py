"""geometry stage: labelled Gaussians -> planning-ready geometry (paper section 3.3).

Modules, one concept each: `options` (GeometryOptions), `filtering` (stage 1, attribute filter),
`clustering` (stage 2, DBSCAN pruning, table plane, background split), `meshing` (stage 3, voxel solid,
alpha shapes, repair, smoothing, decimation, ellipsoid densification), `physics` (stage 4, yaw-only box,
CoACD parts, mass), `metrics` (Chamfer / precision / recall / F1), `convert` (the whole conversion and the
ablation). Writing the twin (and the `splattwin geometry` command, which writes one): `splattwin.twin`.
Test data with a known answer: `splattwin.scene.synthetic`.
"""

from __future__ import annotations

from splattwin._lazy import lazy_exports

# Lazy: nothing is imported until a name is used (`splattwin --help` imports the options modules only).
# (`convert` is also a module's name, so the function stays `splattwin.geometry.convert.convert`)
_EXPORTS = {"GeometryOptions": "options", "scene_scale": "options", "ablation": "convert", "Conversion": "convert",
            "ObjectGeometry": "convert", "BackgroundGeometry": "convert", "fidelity": "metrics", "mesh_fidelity": "metrics",
            "Fidelity": "metrics"}

__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
