"""geometry stage: labelled Gaussians -> planning-ready geometry (paper section 3.3).

Modules, one concept each: `options` (GeometryOptions), `filtering` (stage 1, attribute filter),
`clustering` (stage 2, DBSCAN pruning, table plane, background split), `meshing` (stage 3, voxel solid,
alpha shapes, repair, smoothing, decimation, ellipsoid densification), `physics` (stage 4, yaw-only box,
CoACD parts, mass), `metrics` (Chamfer / precision / recall / F1), `convert` (the whole conversion and the
ablation). Writing the twin (and the `splattwin geometry` command, which writes one): `splattwin.twin`.
Test data with a known answer: `splattwin.scene.synthetic`.
"""
