"""Rendering the road mesh into a camera: projection with distortion, z-buffered rasterisation, and the
differentiable pixel-ray / triangle intersection that carries gradients to the vertex elevations.

Approach (pixel to mesh, like a classic rasteriser; chosen over splatting vertices with grid_sample):
1. `rasterise` projects the vertices (pinhole + radial-tangential distortion), and finds for every pixel
   the nearest triangle covering it with a z-buffer on inverse depth. No gradients: it only decides
   which triangle a pixel sees, so a crest hides the road behind it exactly, with no holes.
2. `ray_triangle_weights` intersects each pixel's viewing ray (undistorted once per camera) with its
   triangle in 3-D (Moller-Trumbore): the perspective-correct barycentric weights are differentiable
   functions of the three vertex elevations. Rendered colour / semantics are the weighted vertex
   attributes, so the colour loss reaches z through the weights (how the pixel slides over the triangle
   when the surface moves) and reaches the codes directly.
The paper's losses are means over image pixels, and its metrics (PSNR, mIoU) compare rendered images
with camera images; rendering pixels keeps training and evaluation on the same footing, and a pixel
subset can be drawn per step for speed without changing what the loss estimates.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
import torch

from mapping.method.road_mesh import used_vertices
from mapping.method.scene_data import CameraModel

NEAR_M = 0.2  # faces with a vertex closer than this (or behind the camera) are not drawn
_MAX_CANDIDATES = 4_000_000  # pixel/face pairs tested at once


def to_camera(T_world_camera: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """Camera-frame coordinates of (M, 3) world points. Written out per axis rather than as `@`: a
    (M, 3) x (3, 3) product goes through multi-threaded BLAS, which ran 20x slower on this 2-core machine
    under load (its threads spin against the other processes)."""
    R, t = T_world_camera[:3, :3], T_world_camera[:3, 3]
    d = points_world - t
    return d[:, 0:1] * R[0] + d[:, 1:2] * R[1] + d[:, 2:3] * R[2]


def to_camera_tensors(T_world_camera: torch.Tensor, points_world: torch.Tensor) -> torch.Tensor:
    """`to_camera` on tensors (float64, on their device), the same arithmetic in the same order."""
    R, t = T_world_camera[:3, :3], T_world_camera[:3, 3]
    d = points_world - t
    return d[:, 0:1] * R[0] + d[:, 1:2] * R[1] + d[:, 2:3] * R[2]


def distort_normalised(x: torch.Tensor, y: torch.Tensor, distortion) -> tuple[torch.Tensor, torch.Tensor]:
    k1, k2, p1, p2, k3 = distortion
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


@lru_cache(maxsize=64)
def _max_r2(name: str, K_bytes: bytes, distortion: tuple, width: int, height: int) -> float:
    """Largest undistorted r^2 seen by the image (corners), with margin: beyond it the distortion
    polynomial can fold far-away points back into the image."""
    K = np.frombuffer(K_bytes).reshape(3, 3)
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], np.float64)
    n = cv2.undistortPoints(
        corners[:, None], K, np.array(distortion),
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10),
    )[:, 0]
    return float((n**2).sum(1).max() * 1.2)


def max_r2(camera: CameraModel) -> float:
    return _max_r2(camera.name, np.ascontiguousarray(camera.K, np.float64).tobytes(), tuple(camera.distortion),
                   camera.width, camera.height)


def project(points_cam: torch.Tensor, camera: CameraModel) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates (N, 2) (pixel centres at integers, as OpenCV) and a validity mask (N,)."""
    z = points_cam[:, 2]
    valid = z > NEAR_M
    zs = torch.where(valid, z, torch.ones_like(z))
    x, y = points_cam[:, 0] / zs, points_cam[:, 1] / zs
    valid = valid & (x * x + y * y <= max_r2(camera))
    if camera.distorted:
        x, y = distort_normalised(x, y, camera.distortion)
    (fx, skew, cx), (_, fy, cy) = camera.K[:2].tolist()
    uv = torch.stack([fx * x + skew * y + cx, fy * y + cy], 1)
    return uv, valid


@lru_cache(maxsize=16)
def _pixel_rays(name: str, K_bytes: bytes, distortion: tuple, width: int, height: int) -> np.ndarray:
    K = np.frombuffer(K_bytes).reshape(3, 3)
    vv, uu = np.mgrid[0:height, 0:width]
    pix = np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float64)
    if any(d != 0 for d in distortion):
        n = cv2.undistortPoints(
            pix[:, None], K, np.array(distortion),
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-9),
        )[:, 0]
    else:
        n = (pix - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T
    rays = np.concatenate([n, np.ones((len(n), 1))], 1).astype(np.float32)
    rays.setflags(write=False)
    return rays


def pixel_rays(camera: CameraModel) -> np.ndarray:
    """(H*W, 3) camera-frame ray directions (x_n, y_n, 1) of every pixel, row-major."""
    return _pixel_rays(camera.name, np.ascontiguousarray(camera.K, np.float64).tobytes(),
                       tuple(camera.distortion), camera.width, camera.height)


def rasterise(
    vertices_world: np.ndarray,
    faces: np.ndarray,
    camera: CameraModel,
    T_world_camera: np.ndarray,
    stride: int = 1,
    offset: tuple[int, int] | None = None,
) -> np.ndarray:
    """Face index (into `faces`) seen by each sampled pixel, -1 for none; shape (H', W') for pixel
    (row i*stride + oy, col j*stride + ox), (oy, ox) = offset (default stride // 2 each)."""
    oy, ox = offset if offset is not None else (stride // 2, stride // 2)
    hs = len(range(oy, camera.height, stride))
    ws = len(range(ox, camera.width, stride))
    if len(faces) == 0:
        return np.full((hs, ws), -1, np.int64)
    if len(vertices_world) > 3 * faces.size:  # project only the vertices these faces use
        used, local = used_vertices(faces, len(vertices_world))
    else:
        used, local = np.arange(len(vertices_world)), faces
    grid = rasterise_tensors(torch.from_numpy(np.ascontiguousarray(vertices_world[used], np.float64)),
                             torch.from_numpy(local.astype(np.int64)), camera,
                             torch.from_numpy(np.ascontiguousarray(T_world_camera, np.float64)), stride, offset)
    return grid.reshape(hs, ws).numpy()


def rasterise_tensors(vertices_world: torch.Tensor, faces: torch.Tensor, camera: CameraModel,
                      T_world_camera: torch.Tensor, stride: int = 1, offset: tuple[int, int] | None = None,
                      max_candidates: int | None = _MAX_CANDIDATES) -> torch.Tensor:
    """`rasterise` on tensors, on their device: vertices (V, 3) float64, faces (F, 3) int64 into them, the pose
    (4, 4) float64; the face seen by each sampled pixel, flat (H' * W',). The pixel / face candidates are tested
    `max_candidates` at a time (the chunks are sized on the host); None: all at once, nothing read back (the
    optimisation loops: about 100 bytes a candidate, some 2 per pixel a face covers)."""
    oy, ox = offset if offset is not None else (stride // 2, stride // 2)
    hs = len(range(oy, camera.height, stride))
    ws = len(range(ox, camera.width, stride))
    device = vertices_world.device
    out = torch.full((hs * ws,), -1, dtype=torch.int64, device=device)
    if len(faces) == 0:
        return out
    cam = to_camera_tensors(T_world_camera, vertices_world).to(torch.float32)
    uv, valid = project(cam, camera)
    g = torch.stack([uv[:, 0] - ox, uv[:, 1] - oy], 1) / stride  # (the offset as scalars: nothing to upload)
    fl = faces
    visible = torch.nonzero(valid[fl].all(1))[:, 0]  # faces with every vertex in front and in the image
    fl = fl[visible]
    fg = g[fl]  # (F, 3, 2)
    lo = torch.ceil(fg.amin(1))
    hi = torch.floor(fg.amax(1))
    lo[:, 0].clamp_(min=0)
    lo[:, 1].clamp_(min=0)
    hi[:, 0].clamp_(max=ws - 1)
    hi[:, 1].clamp_(max=hs - 1)
    n = (hi - lo + 1).clamp(min=0).to(torch.int64)
    count = n[:, 0] * n[:, 1]
    fid = torch.nonzero(count > 0)[:, 0]
    inv_depth = torch.zeros(hs * ws, device=device)
    face_depth = cam[:, 2][fl]
    if max_candidates is None:
        parts: tuple[torch.Tensor, ...] = (fid,)
    else:
        chunk = torch.div(torch.cumsum(count[fid], 0) - 1, max_candidates, rounding_mode="floor")
        parts = torch.split(fid, torch.unique_consecutive(chunk, return_counts=True)[1].tolist())
    cand_f, cand_p, cand_d = [], [], []
    for part in parts:
        f, p, d = _candidates(part, count, n, lo, fg, face_depth, ws)
        inv_depth.scatter_reduce_(0, p, d, "amax")
        cand_f.append(f)
        cand_p.append(p)
        cand_d.append(d)
    for f, p, d in zip(cand_f, cand_p, cand_d, strict=True):
        win = d >= inv_depth[p]  # faces tied at a pixel (a shared edge): the highest face id, whatever the threads
        out.scatter_reduce_(0, p[win], visible[f[win]], "amax")
    return out


def _candidates(fid, count, n, lo, fg, depth, ws):
    """Pixels inside each face of `fid`: (face, flat pixel, inverse depth)."""
    c = count[fid]
    f = torch.repeat_interleave(fid, c)
    first = torch.cumsum(c, 0) - c
    k = torch.arange(len(f), device=f.device) - torch.repeat_interleave(first, c)
    nx = n[f, 0]
    px = lo[f, 0] + (k % nx)
    py = lo[f, 1] + torch.div(k, nx, rounding_mode="floor")
    a, b, cc = fg[f, 0], fg[f, 1], fg[f, 2]
    area = (b[:, 0] - a[:, 0]) * (cc[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (cc[:, 0] - a[:, 0])
    w0 = (b[:, 0] - px) * (cc[:, 1] - py) - (b[:, 1] - py) * (cc[:, 0] - px)
    w1 = (cc[:, 0] - px) * (a[:, 1] - py) - (cc[:, 1] - py) * (a[:, 0] - px)
    w2 = area - w0 - w1
    s = torch.sign(area)
    eps = 1e-6 * area.abs()
    inside = (w0 * s >= -eps) & (w1 * s >= -eps) & (w2 * s >= -eps) & (area.abs() > 1e-12)
    f, px, py = f[inside], px[inside], py[inside]
    w = torch.stack([w0[inside], w1[inside], w2[inside]], 1) / area[inside, None]
    inv_d = (w / depth[f]).sum(1)
    return f, (py * ws + px).to(torch.int64), inv_d


def ray_triangle_weights(rays: torch.Tensor, tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Barycentric weights (P, 3) and ray parameter (P,) where rays (P, 3) from the origin hit the
    triangles tri (P, 3, 3) given relative to the ray origin (Moller-Trumbore; differentiable)."""
    v0, v1, v2 = tri[:, 0], tri[:, 1], tri[:, 2]
    e1, e2 = v1 - v0, v2 - v0
    pvec = torch.linalg.cross(rays, e2)
    det = (e1 * pvec).sum(1)
    det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
    tvec = -v0
    u = (tvec * pvec).sum(1) / det
    qvec = torch.linalg.cross(tvec, e1)
    v = (rays * qvec).sum(1) / det
    t = (e2 * qvec).sum(1) / det
    return torch.stack([1 - u - v, u, v], 1), t


def sampled_pixels(camera: CameraModel, stride: int, offset: tuple[int, int] | None = None) -> np.ndarray:
    """Flat pixel indices (row-major, full image) of the grid `rasterise` samples, shape (H', W')."""
    oy, ox = offset if offset is not None else (stride // 2, stride // 2)
    rows = np.arange(oy, camera.height, stride)
    cols = np.arange(ox, camera.width, stride)
    return rows[:, None] * camera.width + cols[None, :]


def world_rays(T_world_camera: np.ndarray, rays_cam: np.ndarray) -> np.ndarray:
    r, R = rays_cam.astype(np.float64), T_world_camera[:3, :3]
    return r[:, 0:1] * R[:, 0] + r[:, 1:2] * R[:, 1] + r[:, 2:3] * R[:, 2]  # r @ R.T without BLAS (see to_camera)


def world_rays_tensors(T_world_camera: torch.Tensor, rays_cam: torch.Tensor) -> torch.Tensor:
    """`world_rays` on tensors (the pose float64, on their device), the same arithmetic in the same order."""
    r, R = rays_cam.to(torch.float64), T_world_camera[:3, :3]
    return r[:, 0:1] * R[:, 0] + r[:, 1:2] * R[:, 1] + r[:, 2:3] * R[:, 2]
