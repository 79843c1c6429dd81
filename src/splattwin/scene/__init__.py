"""Embedded benchmark scene ("tabletop"): a seeded, ray-traced tabletop with ground truth and simulated
segmenter masks, for testing every later stage without photos (see docs/CONTRACTS.md, "Embedded scene")."""

from splattwin.scene.generate import generate, load_scene, scene_cameras
from splattwin.scene.options import MaskNoise, SceneOptions

__all__ = ["MaskNoise", "SceneOptions", "generate", "load_scene", "scene_cameras"]


def synthetic_gaussians(scene_dir, seed: int = 0, density: float = 40000.0, artefacts: bool = True, **kw):
    """Gaussians on the GT surfaces of a generated scene (+ 3DGS-like artefacts) and labels_gt [N] int32.
    See `splattwin.scene.gaussians.synthetic_gaussians` (imported lazily: it needs the splat stage)."""
    from splattwin.scene.gaussians import synthetic_gaussians as _sg

    return _sg(scene_dir, seed=seed, density=density, artefacts=artefacts, **kw)


__all__ += ["synthetic_gaussians"]
