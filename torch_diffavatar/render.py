"""Preview images of triangle meshes: a small headless z-buffer rasteriser in numpy + Pillow.

Why our own renderer: previews must render on the machines we have (CPU only, no display, no OpenGL /
EGL / OSMesa drivers) and inside tests and CI, without heavy dependencies (pyrender, Open3D, PyTorch3D,
VTK). A vectorised numpy rasteriser is enough for our scale (a 27k-triangle body plus a 10k-triangle
garment at 512×512 in about a second on one core), is deterministic, and gives correct visibility:
every pixel keeps the nearest surface (a z-buffer, not a painter's sort, so cloth lying millimetres
above the body does not speckle; cloth meshes also get a small depth bias toward the camera).

Conventions: world frame Y up, metres, the body facing +Z. ``view="front"`` looks at the body's front
(camera on +Z looking toward −Z), ``"back"`` from −Z, ``"left"``/``"side"`` from +X (the body's left),
``"right"`` from −X; a number is an azimuth in degrees about +Y (0 = front, 90 = left, 180 = back).

Shading: Lambert with ambient, smooth vertex normals, two-sided (a face seen from behind is lit with its
flipped normal, so the inside of a skirt looks like cloth, not a hole).

Limitations: no anti-aliasing beyond optional supersampling, no shadows, no transparency, no textures.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torch_diffavatar.atomic_file import atomic_path

__all__ = [
    "BODY_COLOR",
    "CLOTH_COLOR",
    "CLOTH_DEPTH_BIAS",
    "Camera",
    "RenderMesh",
    "look_at_camera",
    "point_splats",
    "render",
    "render_views",
    "save_png",
]

BODY_COLOR = (205, 180, 160)
CLOTH_COLOR = (70, 110, 190)
CLOTH_DEPTH_BIAS = 0.002  # [m] cloth drawn this much nearer the camera than it is (no z-fighting)

_NAMED_VIEWS = {"front": 0.0, "left": 90.0, "side": 90.0, "back": 180.0, "right": 270.0}
_MAX_CANDIDATES = 4_000_000  # pixel candidates rasterised per chunk (bounds the memory: ~100 MB)


@dataclass
class RenderMesh:
    """One mesh to draw.

    Attributes:
        verts: (V, 3) float positions [m] (numpy array or torch tensor).
        faces: (F, 3) int vertex indices.
        color: RGB in 0..255, or (F, 3) one RGB per face (a heat map, `point_splats`' colours).
        depth_bias: [m] the mesh is drawn as if this much nearer the camera (use `CLOTH_DEPTH_BIAS`
            for cloth lying on a body).
    """

    verts: np.ndarray
    faces: np.ndarray
    color: tuple[int, int, int] | np.ndarray = BODY_COLOR
    depth_bias: float = 0.0


@dataclass
class Camera:
    """A camera looking along ``forward``; pixels are (column, row) with rows going down.

    Attributes:
        position: (3,) eye position [m] (perspective) or a point on the view axis (orthographic).
        right, up, forward: (3,) orthonormal camera axes in the world frame.
        width, height: image size [px].
        scale: orthographic: pixels per metre; perspective: focal length [px].
        center: (2,) pixel of the view axis (column, row).
        perspective: perspective projection if true, else orthographic.
    """

    position: np.ndarray
    right: np.ndarray
    up: np.ndarray
    forward: np.ndarray
    width: int
    height: int
    scale: float
    center: np.ndarray
    perspective: bool = False

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """points: (N, 3) [m] -> pixels (N, 2) float (column, row), view depth (N,) [m] along forward."""
        rel = np.asarray(points, dtype=np.float64) - self.position
        xc, yc, zc = rel @ self.right, rel @ self.up, rel @ self.forward
        if self.perspective:
            inv = 1.0 / np.maximum(zc, 1e-9)
            xc, yc = xc * inv, yc * inv
        pix = np.stack([self.center[0] + self.scale * xc, self.center[1] - self.scale * yc], axis=1)
        return pix, zc


def _as_numpy(a, dtype) -> np.ndarray:
    if hasattr(a, "detach"):  # torch tensor
        a = a.detach().cpu().numpy()
    return np.ascontiguousarray(np.asarray(a, dtype=dtype))


def _check_meshes(meshes) -> list[RenderMesh]:
    if isinstance(meshes, RenderMesh):
        meshes = [meshes]
    out = []
    for k, m in enumerate(meshes):
        if not isinstance(m, RenderMesh):
            m = RenderMesh(*m)
        verts, faces = _as_numpy(m.verts, np.float64), _as_numpy(m.faces, np.int64)
        if verts.ndim != 2 or verts.shape[1] != 3:
            raise ValueError(f"mesh {k}: verts must be (V, 3), got {verts.shape}")
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"mesh {k}: faces must be (F, 3), got {faces.shape}")
        if faces.size and (faces.min() < 0 or faces.max() >= len(verts)):
            raise ValueError(f"mesh {k}: face indices must lie in [0, {len(verts)})")
        if not np.all(np.isfinite(verts)):
            raise ValueError(f"mesh {k}: verts contain NaN or inf")
        color = _as_numpy(m.color, np.float64)
        if color.shape not in ((3,), (len(faces), 3)):
            raise ValueError(f"mesh {k}: color must be RGB or (F, 3) RGB per face, got shape {color.shape}")
        color = tuple(int(c) for c in color) if color.ndim == 1 else color
        out.append(RenderMesh(verts, faces, color, float(m.depth_bias)))
    if not out:
        raise ValueError("render needs at least one mesh")
    return out


def point_splats(
    points, colors, size: float, view: str | float = "front", *, depth_bias: float = 0.0
) -> RenderMesh:
    """Points drawn as one small triangle each, facing a camera at ``view`` (as `render`'s), so that the
    z-buffer decides which points and surfaces are in front.

    Args:
        points: (N, 3) [m]; colors: (N, 3) RGB in 0..255 per point, or one RGB for all.
        size: a triangle's circumradius [m] (about the points' spacing, so that they cover a surface).
        depth_bias: [m] the points drawn as if this much nearer the camera (`RenderMesh`).
    """
    points = _as_numpy(points, np.float64).reshape(-1, 3)
    right, up, _ = _view_axes(view, 0.0)
    corners = size * np.stack([up, -0.87 * right - 0.5 * up, 0.87 * right - 0.5 * up])  # (3, 3)
    verts = (points[:, None, :] + corners[None]).reshape(-1, 3)
    colors = _as_numpy(colors, np.float64)
    colors = colors if colors.ndim == 2 else np.broadcast_to(colors, (len(points), 3))
    return RenderMesh(verts, np.arange(len(verts)).reshape(-1, 3), colors, depth_bias)


def _view_axes(view: str | float, elevation_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, up, forward) for a named view or an azimuth [deg] about +Y (0 = camera on +Z)."""
    if isinstance(view, str):
        if view not in _NAMED_VIEWS:
            raise ValueError(
                f"unknown view {view!r}; use one of {sorted(_NAMED_VIEWS)} or an azimuth in degrees"
            )
        azimuth = _NAMED_VIEWS[view]
    else:
        azimuth = float(view)
    az, el = math.radians(azimuth), math.radians(elevation_deg)
    to_camera = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    forward = -to_camera
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return right, up, forward


def look_at_camera(
    bounds_min,
    bounds_max,
    view: str | float = "front",
    *,
    width: int = 512,
    height: int = 512,
    perspective: bool = False,
    fov_deg: float = 30.0,
    elevation_deg: float = 0.0,
    margin: float = 0.05,
) -> Camera:
    """A camera looking at the centre of an axis-aligned box so that the whole box fits the image.

    Args:
        bounds_min, bounds_max: (3,) box corners [m].
        view: named view or azimuth [deg] (see the module docstring).
        width, height: image size [px].
        perspective: perspective (vertical field of view ``fov_deg``) instead of orthographic.
        elevation_deg: camera raised by this angle above the horizontal [deg].
        margin: free border as a fraction of the image size.
    """
    lo, hi = np.asarray(bounds_min, dtype=np.float64), np.asarray(bounds_max, dtype=np.float64)
    center = 0.5 * (lo + hi)
    right, up, forward = _view_axes(view, elevation_deg)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    rel = corners - center
    half_x = max(np.abs(rel @ right).max(), 1e-6)
    half_y = max(np.abs(rel @ up).max(), 1e-6)
    half_z = np.abs(rel @ forward).max()
    usable = 1.0 - 2.0 * margin
    pix_center = np.array([0.5 * width, 0.5 * height])
    if not perspective:
        scale = usable * min(0.5 * width / half_x, 0.5 * height / half_y)
        position = center - forward * (half_z + 1.0)
        return Camera(position, right, up, forward, width, height, scale, pix_center, False)
    focal = 0.5 * height / math.tan(math.radians(fov_deg) / 2.0)
    # distance at which the box's front face fits: focal * half / (dist - half_z) <= usable * size / 2
    dist = half_z + focal * max(half_x / (0.5 * usable * width), half_y / (0.5 * usable * height))
    return Camera(center - forward * dist, right, up, forward, width, height, focal, pix_center, True)


def _vertex_normals(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted unit vertex normals (V, 3) and unit face normals (F, 3)."""
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    fn = np.cross(v1 - v0, v2 - v0)
    vn = np.zeros_like(verts)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-20)
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-20)
    return vn, fn


def _rasterize(pix: np.ndarray, key: np.ndarray, tris: np.ndarray, width: int, height: int):
    """Z-buffer rasterisation of screen-space triangles.

    Args:
        pix: (V, 2) pixel coordinates (column, row) of all vertices.
        key: (V,) depth key, linear in screen space, smaller = nearer.
        tris: (F, 3) vertex indices.

    Returns:
        tri_id: (H*W,) int64 winning triangle per pixel (-1 = background),
        bary: (H*W, 3) barycentric coordinates of the pixel centre in the winning triangle.
    """
    zbuf = np.full(width * height, np.inf)
    tri_id = np.full(width * height, -1, dtype=np.int64)
    bary = np.zeros((width * height, 3))
    if len(tris) == 0:
        return tri_id, bary
    p0, p1, p2 = pix[tris[:, 0]], pix[tris[:, 1]], pix[tris[:, 2]]
    # signed double area; degenerate (zero-area) triangles cover no pixel centre
    area = (p1[:, 0] - p0[:, 0]) * (p2[:, 1] - p0[:, 1]) - (p1[:, 1] - p0[:, 1]) * (p2[:, 0] - p0[:, 0])
    stack = np.stack([p0, p1, p2], axis=1)  # (F, 3, 2)
    xmin = np.clip(np.ceil(stack[..., 0].min(1) - 0.5), 0, width).astype(np.int64)
    xmax = np.clip(np.floor(stack[..., 0].max(1) - 0.5), -1, width - 1).astype(np.int64)
    ymin = np.clip(np.ceil(stack[..., 1].min(1) - 0.5), 0, height).astype(np.int64)
    ymax = np.clip(np.floor(stack[..., 1].max(1) - 0.5), -1, height - 1).astype(np.int64)
    bw, bh = np.maximum(xmax - xmin + 1, 0), np.maximum(ymax - ymin + 1, 0)
    count = np.where(np.abs(area) > 1e-12, bw * bh, 0)
    live = np.nonzero(count)[0]
    cum = np.cumsum(count[live])
    start = 0
    while start < len(live):
        base = cum[start - 1] if start else 0
        stop = max(int(np.searchsorted(cum, base + _MAX_CANDIDATES, side="right")), start + 1)
        idx = live[start:stop]
        n = count[idx]
        t = np.repeat(idx, n)  # (N,) triangle of each candidate pixel
        offsets = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        px = xmin[t] + offsets % bw[t]
        py = ymin[t] + offsets // bw[t]
        cx, cy = px + 0.5, py + 0.5
        a, b, c = p0[t], p1[t], p2[t]
        inv = 1.0 / area[t]
        w0 = ((b[:, 0] - cx) * (c[:, 1] - cy) - (b[:, 1] - cy) * (c[:, 0] - cx)) * inv
        w1 = ((c[:, 0] - cx) * (a[:, 1] - cy) - (c[:, 1] - cy) * (a[:, 0] - cx)) * inv
        w2 = 1.0 - w0 - w1
        inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
        t, px, py = t[inside], px[inside], py[inside]
        w = np.stack([w0[inside], w1[inside], w2[inside]], axis=1)
        depth = (w * key[tris[t]]).sum(1)
        pid = py * width + px
        # nearest candidate per pixel in this chunk, then merge with the buffer
        order = np.lexsort((depth, pid))
        pid, depth, t, w = pid[order], depth[order], t[order], w[order]
        first = np.ones(len(pid), dtype=bool)
        first[1:] = pid[1:] != pid[:-1]
        pid, depth, t, w = pid[first], depth[first], t[first], w[first]
        better = depth < zbuf[pid]
        pid = pid[better]
        zbuf[pid], tri_id[pid], bary[pid] = depth[better], t[better], w[better]
        start = stop
    return tri_id, bary


def _combine_meshes(meshes: list[RenderMesh], camera: Camera) -> tuple[np.ndarray, ...]:
    """One vertex/triangle list of all ``meshes`` as seen by ``camera``.

    Returns:
        pix (V, 2) pixel coordinates, key (V,) depth key (smaller is nearer; each mesh's depth bias
        applied), tris (F, 3) int triangles (with a perspective camera, none touching the space behind
        the eye), vn (V, 3) unit vertex normals, colors (F, 3) float64 RGB per triangle.
    """
    pix_list, key_list, tri_list, vn_list, tri_color, offset = [], [], [], [], [], 0
    for m in meshes:
        pix, depth = camera.project(m.verts)
        depth = depth - m.depth_bias
        key = -1.0 / np.maximum(depth, 1e-9) if camera.perspective else depth
        faces = m.faces
        color = np.broadcast_to(np.asarray(m.color, dtype=np.float64), (len(faces), 3))
        if camera.perspective:  # drop triangles touching the space behind the eye
            front = (depth[faces] > 1e-6).all(1)
            faces, color = faces[front], color[front]
        vn, _ = _vertex_normals(m.verts, m.faces)
        pix_list.append(pix)
        key_list.append(key)
        vn_list.append(vn)
        tri_list.append(faces + offset)
        tri_color.append(color)
        offset += len(m.verts)
    pix, key, tris = np.concatenate(pix_list), np.concatenate(key_list), np.concatenate(tri_list)
    return pix, key, tris, np.concatenate(vn_list), np.concatenate(tri_color)


def _view_directions(camera: Camera, pixel: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, 3) direction from the eye through each hit pixel (flat indices ``pixel`` (H,) into the
    supersampled image), world frame; ``shape`` (H, 3). Orthographic: the camera's forward."""
    if not camera.perspective:
        return np.broadcast_to(camera.forward, shape)
    sw = camera.width
    ray = np.stack(
        [
            (pixel % sw + 0.5 - camera.center[0]) / camera.scale,
            -(pixel // sw + 0.5 - camera.center[1]) / camera.scale,
            np.ones(len(pixel)),
        ],
        axis=1,
    )
    return ray @ np.stack([camera.right, camera.up, camera.forward])


def _shade(n: np.ndarray, view_dir: np.ndarray, camera: Camera, ambient: float) -> np.ndarray:
    """(H,) brightness in [0, 1] of surface points with unit normals ``n`` (H, 3) seen along
    ``view_dir`` (H, 3): ambient plus two-sided Lambert from a key and a fill light."""
    # two-sided: normals facing away from the eye are flipped toward it
    n = np.where(((n * view_dir).sum(1) > 0)[:, None], -n, n)
    # key light from above-left of the camera, a weaker fill from the right
    key_light = -camera.forward + 0.5 * camera.up + 0.3 * (-camera.right)
    fill_light = -camera.forward - 0.2 * camera.up + 0.6 * camera.right
    key_light /= np.linalg.norm(key_light)
    fill_light /= np.linalg.norm(fill_light)
    diffuse = 0.8 * np.clip(n @ key_light, 0, None) + 0.25 * np.clip(n @ fill_light, 0, None)
    return ambient + (1.0 - ambient) * np.clip(diffuse, 0.0, 1.0)


def render(
    meshes: RenderMesh | Iterable[RenderMesh | tuple],
    *,
    view: str | float = "front",
    width: int = 512,
    height: int = 512,
    camera: Camera | None = None,
    perspective: bool = False,
    elevation_deg: float = 0.0,
    background: tuple[int, int, int] = (255, 255, 255),
    ambient: float = 0.3,
    supersample: int = 1,
) -> np.ndarray:
    """Render meshes into an RGB image.

    Args:
        meshes: `RenderMesh` objects or tuples ``(verts (V,3), faces (F,3), color[, depth_bias])``.
        view: named view or azimuth [deg] about +Y (see the module docstring); ignored with ``camera``.
        width, height: output size [px].
        camera: explicit camera (its width/height must equal ``width``/``height`` × ``supersample``);
            default: `look_at_camera` on the meshes' bounds.
        perspective: perspective instead of orthographic projection (default camera only).
        elevation_deg: camera elevation above the horizontal [deg] (default camera only).
        background: RGB of empty pixels.
        ambient: ambient light fraction in [0, 1]; the rest is Lambert from a light near the camera.
        supersample: render at this factor and average down (anti-aliasing), 1 = off.

    Returns:
        (height, width, 3) uint8 image.
    """
    meshes = _check_meshes(meshes)
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    sw, sh = width * supersample, height * supersample
    if camera is None:
        lo = np.min([m.verts.min(0) for m in meshes if len(m.verts)], axis=0)
        hi = np.max([m.verts.max(0) for m in meshes if len(m.verts)], axis=0)
        camera = look_at_camera(
            lo, hi, view, width=sw, height=sh, perspective=perspective, elevation_deg=elevation_deg
        )
    elif (camera.width, camera.height) != (sw, sh):
        raise ValueError(f"camera is {camera.width}x{camera.height}, expected {sw}x{sh}")
    pix, key, tris, vn, colors = _combine_meshes(meshes, camera)
    tri_id, bary = _rasterize(pix, key, tris, sw, sh)

    image = np.empty((sh * sw, 3))
    image[:] = np.asarray(background, dtype=np.float64)
    hit = tri_id >= 0
    t = tri_id[hit]
    n = (bary[hit][:, :, None] * vn[tris[t]]).sum(1)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
    shade = _shade(n, _view_directions(camera, np.nonzero(hit)[0], n.shape), camera, ambient)
    image[hit] = colors[t] * shade[:, None]
    image = image.reshape(sh, sw, 3)
    if supersample > 1:
        image = image.reshape(height, supersample, width, supersample, 3).mean(axis=(1, 3))
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def render_views(
    meshes: RenderMesh | Iterable[RenderMesh | tuple],
    views: Sequence[str | float] = ("front", "back"),
    *,
    width: int = 512,
    height: int = 512,
    **kwargs,
) -> np.ndarray:
    """Render several views side by side: (height, width × len(views), 3) uint8.

    Every view uses the same bounds (the meshes' box) so the scale is the same across views in
    orthographic mode. Other keyword arguments go to `render`.
    """
    meshes = _check_meshes(meshes)
    if not views:
        raise ValueError("render_views needs at least one view")
    return np.concatenate(
        [render(meshes, view=v, width=width, height=height, **kwargs) for v in views], axis=1
    )


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write an (H, W, 3) uint8 image as PNG; creates the parent folder. Returns the path."""
    from PIL import Image

    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"image must be (H, W, 3) uint8, got {image.shape} {image.dtype}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp)
    return path
