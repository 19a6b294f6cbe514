"""Camera conventions, intrinsics, rays and similarity transforms (numpy only).

This module is the single owner of camera maths in the project. Everything else imports it.

Conventions (see docs/dataset-format.md):

* Poses are 4x4 ``camera_to_world`` matrices in the **OpenCV** camera frame: +x right,
  +y down, +z forward (the viewing direction). Blender/OpenGL cameras look down -z with +y up;
  :func:`opencv_from_opengl` and :func:`opengl_from_opencv` convert between the two (the same
  right-multiplication by ``diag(1, -1, -1, 1)``, which is its own inverse).
* Intrinsics are in pixel units. Pixel ``(u, v)`` covers ``[u, u+1) x [v, v+1)``; its centre is
  ``(u + 0.5, v + 0.5)``; a centred principal point is ``(W/2, H/2)``.
* Depth is *planar* (the camera-frame z of the hit point), as Blender's depth pass gives it.
  Rays from :func:`pixel_rays` have unit camera-frame z, so ``origin + depth * direction`` is
  the 3D point of a pixel with planar depth ``depth``. A distance along the ray (what NeRF
  renderers such as nerfstudio's call depth) is planar depth times :func:`ray_lengths`.
"""

from __future__ import annotations

import math

import numpy as np

#: Right-multiplying a camera-to-world matrix by this flips between OpenCV and OpenGL frames.
CV_GL_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def opencv_from_opengl(c2w_gl: np.ndarray) -> np.ndarray:
    """Convert camera-to-world pose(s) ``(..., 4, 4)`` from OpenGL/Blender to OpenCV frames."""
    return np.asarray(c2w_gl, dtype=np.float64) @ CV_GL_FLIP


def opengl_from_opencv(c2w_cv: np.ndarray) -> np.ndarray:
    """Convert camera-to-world pose(s) ``(..., 4, 4)`` from OpenCV to OpenGL/Blender frames."""
    return np.asarray(c2w_cv, dtype=np.float64) @ CV_GL_FLIP


def intrinsics_from_fov(fov_x_deg: float, width: int, height: int) -> np.ndarray:
    """3x3 pixel-unit intrinsics for a horizontal field of view, square pixels, centred.

    This matches Blender's camera with ``sensor_fit='HORIZONTAL'`` (or ``'AUTO'`` when
    ``width >= height``) and ``angle = fov_x``.
    """
    if not (0.0 < fov_x_deg < 180.0):
        raise ValueError(f"field of view must be in (0, 180) degrees, got {fov_x_deg}")
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2.0)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def fov_from_intrinsics(K: np.ndarray, width: int) -> float:
    """Horizontal field of view in degrees of pixel-unit intrinsics ``K`` for an image width."""
    return math.degrees(2.0 * math.atan(0.5 * width / float(K[0, 0])))


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """3x3 intrinsics from its four parameters."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def pixel_rays(
    K: np.ndarray, c2w: np.ndarray, width: int, height: int, pixels: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays through pixel centres of an OpenCV camera.

    Args:
        K: 3x3 pixel-unit intrinsics.
        c2w: 4x4 OpenCV camera-to-world pose.
        width, height: image size (used when ``pixels`` is None).
        pixels: optional ``(N, 2)`` integer ``(u, v)`` = (column, row) pixel indices.

    Returns:
        ``origins`` and ``directions``, each ``(H*W, 3)`` in row-major pixel order (or ``(N, 3)``).
        Directions are *not* normalised: their camera-frame z is 1, so a planar depth ``d``
        gives the point ``origin + d * direction``.
    """
    if pixels is None:
        v, u = np.mgrid[0:height, 0:width]
        u = u.reshape(-1)
        v = v.reshape(-1)
    else:
        pixels = np.asarray(pixels)
        u, v = pixels[:, 0], pixels[:, 1]
    x = (u + 0.5 - K[0, 2]) / K[0, 0]
    y = (v + 0.5 - K[1, 2]) / K[1, 1]
    d_cam = np.stack([x, y, np.ones_like(x, dtype=np.float64)], axis=-1)
    c2w = np.asarray(c2w, dtype=np.float64)
    directions = d_cam @ c2w[:3, :3].T
    origins = np.broadcast_to(c2w[:3, 3], directions.shape).copy()
    return origins, directions


def ray_lengths(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """``(H, W)``: the distance from the camera centre to the point of planar depth 1 on each
    pixel-centre ray (``|d|`` of :func:`pixel_rays`' directions, which are rotated but not scaled by
    the pose). A depth measured along the ray (nerfstudio's NeRF depth) is planar depth times this.
    """
    _, d = pixel_rays(K, np.eye(4), width, height)
    return np.linalg.norm(d, axis=1).reshape(height, width)


def planar_from_ray_depth(ray_depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Planar depth (camera-frame z) of ``(H, W)`` depths measured along the pixel-centre rays
    (float64; ``+inf`` stays ``+inf``)."""
    ray_depth = np.asarray(ray_depth, dtype=np.float64)
    return ray_depth / ray_lengths(K, ray_depth.shape[1], ray_depth.shape[0])


def project(points_world: np.ndarray, K: np.ndarray, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points ``(N, 3)`` into an OpenCV camera.

    Returns ``(uv, depth)``: continuous pixel coordinates (pixel centres at ``.5``) and planar
    depth. Points behind the camera get a non-positive depth; their ``uv`` is meaningless.
    """
    w2c = invert_pose(c2w)
    p = np.asarray(points_world, dtype=np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    z = p[:, 2]
    safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
    uv = np.stack([K[0, 0] * p[:, 0] / safe + K[0, 2], K[1, 1] * p[:, 1] / safe + K[1, 2]], axis=-1)
    return uv, z


def project_pixels(points_world: np.ndarray, K: np.ndarray, c2w: np.ndarray, width: int, height: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Project world points ``(N, 3)`` onto the pixels of a ``width`` x ``height`` image.

    Returns ``(uv, depth, pix, inside)``: :func:`project`'s continuous ``uv (N, 2)`` and planar
    ``depth (N,)``, the integer pixel ``pix (N, 2)`` = (column, row) each point falls in (``-1``
    behind the camera), and ``inside (N,)``: in front of the camera and within the image.
    """
    uv, z = project(points_world, K, c2w)
    front = z > 0
    pix = np.full((len(z), 2), -1, dtype=np.int64)
    pix[front] = np.floor(uv[front]).astype(np.int64)
    inside = front & (pix[:, 0] >= 0) & (pix[:, 0] < width) & (pix[:, 1] >= 0) & (pix[:, 1] < height)
    return uv, z, pix, inside


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid or similarity transform(s) ``(..., 4, 4)`` with last row ``0 0 0 1``."""
    T = np.asarray(T, dtype=np.float64)
    A = T[..., :3, :3]
    A_inv = np.linalg.inv(A)
    out = np.zeros_like(T)
    out[..., :3, :3] = A_inv
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", A_inv, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def scale_about(center: np.ndarray, s: float) -> np.ndarray:
    """4x4 similarity that scales space by ``s`` about the point ``center``.

    This is how a configuration is defined: object k at time t is moved by
    ``scale_about(c_t, s_k) @ pose_k(t)`` where ``c_t`` is the training camera centre.
    """
    if not (np.isfinite(s) and s > 0):
        raise ValueError(f"scale must be finite and positive, got {s}")
    T = np.eye(4)
    T[:3, :3] *= s
    T[:3, 3] = (1.0 - s) * np.asarray(center, dtype=np.float64)
    return T


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV camera-to-world pose at ``eye`` looking at ``target`` with world ``up`` (default +z)."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    n = np.linalg.norm(forward)
    if n < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z = forward / n
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to the up vector")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Geodesic angle in degrees between two rotation matrices.

    ``atan2(sin, cos)`` of the relative rotation, not ``acos(cos)``: acos loses half the digits
    near 0 and 180 degrees (1.7e-6 degrees off at 180), atan2 keeps full precision everywhere.
    """
    R = np.asarray(R_a)[:3, :3].T @ np.asarray(R_b)[:3, :3]
    c = (np.trace(R) - 1.0) / 2.0
    s = 0.5 * math.sqrt((R[2, 1] - R[1, 2]) ** 2 + (R[0, 2] - R[2, 0]) ** 2 + (R[1, 0] - R[0, 1]) ** 2)
    return math.degrees(math.atan2(s, c))


def fit_similarity(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares similarity (Umeyama) mapping points ``src (N,3)`` onto ``dst (N,3)``.

    Returns a 4x4 matrix ``T`` with ``dst ~ T[:3,:3] @ src + T[:3,3]`` where ``T[:3,:3] = s R``.
    Raises ``ValueError`` for fewer than 3 points or degenerate (collinear / coincident) input.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ValueError(f"fit_similarity needs two (N>=3, 3) arrays, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = (xs**2).sum() / len(src)
    if var_s < 1e-18:
        raise ValueError("fit_similarity: source points coincide")
    cov = xd.T @ xs / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    if np.sum(S > 1e-12 * max(S[0], 1e-300)) < 2:
        raise ValueError("fit_similarity: points are collinear")
    R = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / var_s
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = mu_d - s * R @ mu_s
    return T


def fit_pose_similarity(src_c2w: np.ndarray, dst_c2w: np.ndarray) -> np.ndarray:
    """Similarity ``T`` aligning camera poses ``src (N,4,4)`` to ``dst (N,4,4)``: ``dst ~ T @ src``.

    The rotation averages the per-camera orientation differences (projected onto SO(3)), then
    scale and translation fit the camera centres by least squares. Unlike
    :func:`fit_similarity` on centres alone, this works for a single camera or centres on a line,
    as long as two centres differ (for the scale); with one centre the scale is 1.
    """
    src = np.asarray(src_c2w, dtype=np.float64)
    dst = np.asarray(dst_c2w, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 3 or src.shape[1:] != (4, 4) or len(src) == 0:
        raise ValueError(f"fit_pose_similarity needs two (N, 4, 4) arrays, got {src.shape} and {dst.shape}")
    M = np.einsum("nij,nkj->ik", dst[:, :3, :3], src[:, :3, :3])  # sum of R_dst R_src^T
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    x = src[:, :3, 3] @ R.T
    c = dst[:, :3, 3]
    xm, cm = x.mean(0), c.mean(0)
    var = ((x - xm) ** 2).sum()
    s = float(((x - xm) * (c - cm)).sum() / var) if var > 1e-18 else 1.0
    if s <= 0:
        raise ValueError("fit_pose_similarity: camera centres give a negative scale (poses disagree)")
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = cm - s * xm
    return T
