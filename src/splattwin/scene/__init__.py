"""Embedded benchmark scene ("tabletop"): a seeded, ray-traced tabletop with ground truth and simulated
segmenter masks, for testing every later stage without photos (see docs/CONTRACTS.md, "Embedded scene").

`splattwin.scene.synthetic`: smaller generators with a known answer for the tests and benchmarks of the
semantics and geometry stages. The package sits above every stage (it uses their types to build test
data); only the pipeline, the tests and the benchmarks import it. Imports are lazy
(`splattwin.scene.options` is read by `splattwin --help` and must not pull in Open3D).
"""

from __future__ import annotations

from splattwin._lazy import lazy_exports

_EXPORTS = {"generate": "generator", "load_scene": "generator", "scene_cameras": "generator",
            "MaskNoise": "options", "SceneOptions": "options"}

__all__ = [*_EXPORTS, "synthetic_gaussians"]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)


def synthetic_gaussians(scene_dir, seed: int = 0, density: float = 40000.0, artefacts: bool = True, **kw):
    """Gaussians on the GT surfaces of a generated scene (+ 3DGS-like artefacts) and labels_gt [N] int32.
    See `splattwin.scene.gaussians.synthetic_gaussians`."""
    from splattwin.scene.gaussians import synthetic_gaussians as _sg

    return _sg(scene_dir, seed=seed, density=density, artefacts=artefacts, **kw)
