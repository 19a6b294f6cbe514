import numpy as np
import pytest

from scenecore import cameras as C


def random_pose(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = rng.normal(size=3) * 3
    return T


def test_cv_gl_round_trip_and_axes():
    rng = np.random.default_rng(0)
    T = random_pose(rng)
    assert np.allclose(C.opencv_from_opengl(C.opengl_from_opencv(T)), T)
    gl = C.opengl_from_opencv(T)
    # OpenGL looks down -z: its -z axis equals OpenCV's +z (forward); +y up is -y down.
    assert np.allclose(-gl[:3, 2], T[:3, 2])
    assert np.allclose(-gl[:3, 1], T[:3, 1])
    assert np.allclose(gl[:3, 3], T[:3, 3])


@pytest.mark.parametrize("fov,w,h", [(40.0, 128, 128), (90.0, 640, 480), (1.0, 16, 9), (170.0, 7, 300)])
def test_intrinsics_fov_round_trip(fov, w, h):
    K = C.intrinsics_from_fov(fov, w, h)
    assert K[0, 2] == w / 2 and K[1, 2] == h / 2
    assert C.fov_from_intrinsics(K, w) == pytest.approx(fov, rel=1e-12)


def test_bad_fov_rejected():
    with pytest.raises(ValueError, match="field of view"):
        C.intrinsics_from_fov(0.0, 10, 10)


def camera_and_pixels(seed: int, W: int = 32, H: int = 24, n: int = 50):
    """A random camera's intrinsics and pose, and ``n`` random pixels with planar depths."""
    rng = np.random.default_rng(seed)
    K = C.intrinsics_from_fov(55.0, W, H)
    c2w = random_pose(rng)
    pix = np.stack([rng.integers(0, W, n), rng.integers(0, H, n)], axis=1)
    return rng, K, c2w, pix, rng.uniform(0.01, 1e3, n)


def test_rays_hit_known_points():
    W, H = 32, 24
    _, K, c2w, pix, depth = camera_and_pixels(1, W, H)
    # Points placed exactly on pixel-centre rays at known planar depths are recovered.
    o, d = C.pixel_rays(K, c2w, W, H, pixels=pix)
    pts = o + depth[:, None] * d
    uv, z = C.project(pts, K, c2w)
    assert np.allclose(uv, pix + 0.5, atol=1e-6)
    assert np.allclose(z, depth, rtol=1e-10)
    # Full-image rays are row-major and the centre ray of a centred camera is the forward axis.
    o, d = C.pixel_rays(K, np.eye(4), W, H)
    assert d.shape == (W * H, 3)
    assert np.allclose(d[0], [(0.5 - W / 2) / K[0, 0], (0.5 - H / 2) / K[1, 1], 1.0])
    assert np.allclose(d[1, 0] - d[0, 0], 1 / K[0, 0])


def test_project_pixels_finds_the_pixel_of_each_point():
    W, H = 32, 24
    rng, K, c2w, pix, depth = camera_and_pixels(2, W, H)
    # Points inside known pixels (offsets within the pixel) land in those pixels, at their depths.
    x = (pix + rng.uniform(0.05, 0.95, (50, 2)) - K[:2, 2]) / np.diag(K)[:2]
    cam = np.concatenate([x * depth[:, None], depth[:, None]], axis=1)
    pts = cam @ c2w[:3, :3].T + c2w[:3, 3]
    # and three that do not: behind the camera, left of the image, below it.
    extra = np.array([[0.0, 0.0, -1.0], [-2.0 * W / K[0, 0], 0.0, 1.0], [0.0, 2.0 * H / K[1, 1], 1.0]])
    pts = np.concatenate([pts, extra @ c2w[:3, :3].T + c2w[:3, 3]])
    uv, z, got, inside = C.project_pixels(pts, K, c2w, W, H)
    assert np.array_equal(got[:50], pix) and inside[:50].all()
    assert np.allclose(z[:50], depth, rtol=1e-10)
    assert not inside[50:].any() and (got[50] == -1).all() and got[51, 0] < 0 and got[52, 1] >= H
    assert np.allclose(uv, C.project(pts, K, c2w)[0])


def test_scale_about_keeps_center_and_camera_ray():
    c = np.array([1.0, -2.0, 0.5])
    S = C.scale_about(c, 3.0)
    assert np.allclose(S @ np.r_[c, 1], np.r_[c, 1])
    p = np.array([2.0, 0.0, 1.0])
    q = (S @ np.r_[p, 1])[:3]
    # Scaling about the camera centre keeps a point on its ray, with depth multiplied by s.
    assert np.allclose(q - c, 3.0 * (p - c))
    with pytest.raises(ValueError):
        C.scale_about(c, 0.0)


def test_invert_pose_similarity():
    rng = np.random.default_rng(2)
    T = random_pose(rng) @ C.scale_about(np.zeros(3), 2.5)
    assert np.allclose(C.invert_pose(T) @ T, np.eye(4))


def test_fit_similarity_recovers_transform():
    rng = np.random.default_rng(3)
    T = random_pose(rng)
    T[:3, :3] *= 0.37
    src = rng.normal(size=(20, 3))
    dst = src @ T[:3, :3].T + T[:3, 3]
    assert np.allclose(C.fit_similarity(src, dst), T, atol=1e-9)
    with pytest.raises(ValueError, match="collinear"):
        line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
        C.fit_similarity(line, line)


def test_look_at_points_forward():
    T = C.look_at(np.array([0.0, -5.0, 1.0]), np.array([0.0, 0.0, 1.0]))
    assert np.allclose(T[:3, 2], [0, 1, 0])
    assert np.allclose(T[:3, 1], [0, 0, -1])  # image y points down = world -z
    assert C.rotation_angle_deg(T, T) == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("deg", [1e-5, 0.5, 1.0, 30.0, 90.0, 179.0, 180.0])
def test_rotation_angle_is_the_geodesic_angle(deg: float):
    """The SfM accuracy figures rest on this: the angle of R_a^T R_b about any axis, in degrees,
    symmetric and independent of a common rotation applied to both."""
    rng = np.random.default_rng(int(deg * 10))
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    a = np.radians(deg)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K  # Rodrigues
    Q = random_pose(rng)[:3, :3]
    assert C.rotation_angle_deg(np.eye(3), R) == pytest.approx(deg, abs=1e-6)
    assert C.rotation_angle_deg(R, np.eye(3)) == pytest.approx(deg, abs=1e-6)
    assert C.rotation_angle_deg(Q, Q @ R) == pytest.approx(deg, abs=1e-6)
    # relative precision too, which acos(trace) loses near 0 (0.4% off at 1e-5 degrees)
    assert C.rotation_angle_deg(np.eye(3), R) == pytest.approx(deg, rel=1e-6)


def test_fit_pose_similarity_recovers_transform_even_for_collinear_centres():
    rng = np.random.default_rng(4)
    T = random_pose(rng)
    T[:3, :3] *= 2.3
    src = np.stack([random_pose(rng) for _ in range(6)])
    src[:, :3, 3] = np.outer(np.arange(6.0), [1.0, 0.5, -0.2])  # centres on a line
    dst = T[None] @ src
    dst[:, :3, :3] /= 2.3  # poses stay rigid; the scale lives in the centres
    assert np.allclose(C.fit_pose_similarity(src, dst), T, atol=1e-9)
