import numpy as np
from scipy.spatial.transform import Rotation

from splattwin.splat.gaussians import Gaussians
from splattwin.twin.splats import eval_sh, sh_basis, sh_rotation, transform_gaussians, write_object_splats


def _random_gaussians(n=40, degree=3, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return Gaussians(rng.normal(size=(n, 3)), q / np.linalg.norm(q, axis=1, keepdims=True),
                     np.abs(rng.normal(size=(n, 3))) * 0.01, rng.uniform(0.1, 0.9, n),
                     rng.normal(size=(n, (degree + 1) ** 2, 3)))


def test_sh_basis_matches_3dgs_closed_forms():
    d = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    B = sh_basis(d, 1)
    C0, C1 = 0.28209479177387814, 0.4886025119029199
    assert np.allclose(B[:, 0], C0)
    assert np.allclose(B[0, 1:], [0, C1, 0]) and np.allclose(B[1, 1:], [0, 0, -C1]) and np.allclose(B[2, 1:], [-C1, 0, 0])


def test_sh_rotation_is_orthogonal_and_exact():
    R = Rotation.random(random_state=3).as_matrix()
    D = sh_rotation(R, 3)
    assert np.allclose(D @ D.T, np.eye(16), atol=1e-9)
    rng = np.random.default_rng(4)
    d = rng.normal(size=(100, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    assert np.allclose(sh_basis(d, 3) @ D, sh_basis(d @ R.T, 3), atol=1e-9)


def test_transform_gaussians_preserves_appearance():
    g = _random_gaussians()
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=5).as_matrix()
    T[:3, 3] = [0.3, -0.2, 0.1]
    h = transform_gaussians(g, T)
    R = T[:3, :3]
    assert np.allclose(h.means, g.means @ R.T + T[:3, 3])
    assert np.allclose(h.covariances(), R @ g.covariances() @ R.T, atol=1e-12)
    d = np.random.default_rng(6).normal(size=(len(g), 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # the same viewing ray, expressed in each frame, sees the same colour
    assert np.allclose(eval_sh(h.sh, d @ R.T), eval_sh(g.sh, d), atol=1e-9)
    assert np.allclose(h.opacities, g.opacities) and np.allclose(h.scales, g.scales)


def test_write_object_splats_round_trip(tmp_path):
    g = _random_gaussians(degree=1)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 0.7).as_matrix()
    T[:3, 3] = [0.1, 0.2, 0.05]
    p = write_object_splats(tmp_path / "obj" / "splats.ply", g, T)
    back = Gaussians.load_ply(p)
    world = back.means @ T[:3, :3].T + T[:3, 3]
    assert np.allclose(world, g.means, atol=1e-6)
    assert back.sh_degree == 1 and len(back) == len(g)
