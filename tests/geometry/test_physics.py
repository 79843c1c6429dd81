import numpy as np
import trimesh

from splattwin.geometry.physics import convex_parts, convexity, mass_properties, yaw_obb


def test_yaw_obb_of_rotated_box():
    box = trimesh.creation.box([0.2, 0.08, 0.05])
    T = trimesh.transformations.rotation_matrix(2.0, [0, 0, 1])
    T[:3, 3] = [0.1, -0.2, 0.025]
    box.apply_transform(T)
    pts = trimesh.sample.sample_surface(box, 4000, seed=0)[0]
    ob = yaw_obb(pts)
    assert np.allclose(ob.extent, [0.2, 0.08, 0.05], atol=2e-3)
    assert np.allclose(ob.T_world_box[:3, 3], T[:3, 3], atol=2e-3)
    # yaw is 2.0 rad modulo pi (box symmetry), canonicalised to (-pi/2, pi/2]
    assert np.isclose(ob.yaw, 2.0 - np.pi, atol=0.02)
    assert np.allclose(ob.T_world_box[2, :3], [0, 0, 1])


def test_convexity_and_decomposition_of_l_shape():
    a = trimesh.creation.box([0.2, 0.04, 0.04])
    b = trimesh.creation.box([0.04, 0.16, 0.04])
    b.apply_translation([0.08, 0.06, 0])
    L = trimesh.boolean.union([a, b])
    assert convexity(trimesh.creation.box([0.1, 0.1, 0.1])) > 0.999
    assert convexity(L) < 0.7
    parts = convex_parts(L, convex_ratio=0.85)
    assert len(parts) >= 2 and all(p.is_convex for p in parts)
    assert abs(sum(p.volume for p in parts) - L.volume) / L.volume < 0.15
    assert len(convex_parts(trimesh.creation.box([0.1, 0.1, 0.1]))) == 1


def test_mass_from_density():
    v, m = mass_properties(trimesh.creation.box([0.1, 0.2, 0.05]), 800.0)
    assert np.isclose(v, 0.001) and np.isclose(m, 0.8)
