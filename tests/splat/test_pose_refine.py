from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import torch

from splattwin.splat.pose_refine import PoseCorrection, se3_exp
from splattwin.splat.rasterization import rasterization

_spec = importlib.util.spec_from_file_location("_splat_trainer_helpers", Path(__file__).with_name("test_trainer.py"))
helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(helpers)


def test_se3_exp_matches_closed_form():
    xi = torch.tensor([[0.1, -0.2, 0.3, 0.0, 0.0, math.pi / 2]], dtype=torch.float64)
    T = se3_exp(xi)[0]
    torch.testing.assert_close(T[:3, :3], torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64),
                               atol=1e-12, rtol=0)
    torch.testing.assert_close(se3_exp(torch.zeros(2, 6)), torch.eye(4).expand(2, 4, 4))
    # pure translation
    torch.testing.assert_close(se3_exp(torch.tensor([[1.0, 2, 3, 0, 0, 0]]))[0, :3, 3], torch.tensor([1.0, 2, 3]))


def _pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    dR = T_a[:3, :3] @ T_b[:3, :3].T
    ang = math.degrees(math.acos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    return ang, float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))


def test_pose_refinement_recovers_perturbation():
    g = helpers.gt_gaussians()
    cam = helpers.ring_cameras(1, width=64, height=48)[0]
    target = torch.from_numpy(helpers.render_gaussians(g, cam))
    T_true = cam.T_cam_world
    xi_pert = torch.tensor([[0.012, -0.008, 0.01, 0.01, -0.015, 0.012]], dtype=torch.float64)  # ~1.2 deg, 1.8 cm
    T_pert = se3_exp(xi_pert)[0].numpy() @ T_true
    ang0, tr0 = _pose_error(T_pert, T_true)
    t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    means, quats, scales, ops, sh = t(g.means), t(g.quats), t(g.scales), t(g.opacities), t(g.sh)
    pc = PoseCorrection(1, lr=2e-3)
    vm = t(T_pert)[None]
    K = t(cam.K)[None]
    for _ in range(150):
        img, _, _ = rasterization(means, quats, scales, ops, sh, pc.apply(vm, [0]), K, cam.width, cam.height,
                                  sh_degree=0, backend="cpu")
        loss = ((img[0] - target) ** 2).mean()
        loss.backward()
        pc.step([0])
    ang1, tr1 = _pose_error(pc.corrected(T_pert[None])[0], T_true)
    assert ang1 < 0.3 * ang0 and tr1 < 0.3 * tr0, (ang0, ang1, tr0, tr1)


def test_remove_common_motion_cancels_a_shared_world_motion():
    from splattwin.splat.pose_refine import adjoint

    cams = helpers.ring_cameras(4)
    T_cw = torch.tensor(np.stack([c.T_cam_world for c in cams]), dtype=torch.float64)
    w = torch.tensor([0.01, -0.02, 0.005, 0.01, 0.0, -0.01], dtype=torch.float64)  # one world-frame motion
    xi = (adjoint(T_cw) @ w[None, :, None])[..., 0]  # as seen from each camera
    # the camera-frame twists really are the same world motion: exp(xi_c) T_cw = T_cw exp(w)
    torch.testing.assert_close(se3_exp(xi) @ T_cw, T_cw @ se3_exp(w)[None].expand(4, 4, 4))
    pc = PoseCorrection(4)
    with torch.no_grad():
        for p, v in zip(pc.params, xi):
            p.copy_(v)
        pc.params[0].add_(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 0.004]))  # plus one individual correction
    pc.remove_common_motion(T_cw.float())
    left = pc.xi.detach()
    assert left[1:].abs().max() < 2e-3 and left[0, 5].abs() > 2e-3
