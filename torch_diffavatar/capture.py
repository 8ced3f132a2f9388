"""A simulated multi-camera depth capture of a scene of labelled triangle meshes (issue #29).

Real captures differ from our clean synthetic scans: points come from depth cameras (only what a camera
sees, nothing under the arms or between the legs, noise growing with distance, no return at grazing
angles), the floor is in view (about half the points), a few stray points float around, the person faces
any direction, and files come in centimetres or millimetres with Y pointing down. `capture_scene`
produces all of that from meshes in our world frame (Y up, metres, floor at y = 0):

1. each `DepthCamera` (a pinhole; `ring_cameras`: N around the person, `front_camera`: one in front)
   renders the meshes and the floor (a square at y = 0, ray-cast exactly) into a z-buffer: the
   triangles are rasterised in numpy (`render`'s rasteriser) with perspective-correct depth per pixel;
2. every pixel with a return is back-projected to a point, with the normal of its triangle (turned
   towards the camera), the colour of its mesh (+ Gaussian noise of ``color_noise`` levels) and its label;
3. pixels seen at a grazing angle (|cos(view ray, normal)| < ``min_cos``) are dropped, and the depth gets
   Gaussian noise along the ray with sigma = ``noise_a + noise_b · d²`` (d the depth [m]); the default
   2 mm + 1.5 mm/m² (7.8 mm at 2 m) lies between Kinect v1 (Nguyen et al. 2012: 1.2 mm + 1.9 mm · (d −
   0.4 m)² / m²) and time-of-flight sensors;
4. real rigs add what a single ideal camera does not (both off by default): **mixed pixels**
   (``flying_pixels``: a share of the pixels at a depth jump return a depth between the two surfaces,
   their colours mixed, as time-of-flight and stereo sensors do at silhouettes) and **calibration error**
   (``calibration_m``, ``calibration_deg``: each camera's points placed with a pose that is off by a
   random translation and rotation, so that the views overlap as slightly shifted surfaces);
5. ``stray_fraction`` of the points are added uniformly in the box around the scene (dust, a cable):
   label `STRAY_LABEL`;
6. the whole capture turns by ``yaw_deg`` about the vertical axis through the origin, and is written in
   the asked ``units`` and ``up`` axis (the `scan.UNITS` and `scan.UP_AXES` of `scan.load_scan`: loading the
   file with the same options gives back the yawed scene in metres, Y up, floor at y = 0).

Labels: those of the meshes (1 garment, 0 skin by our convention), `FLOOR_LABEL` (-1) on the floor,
`STRAY_LABEL` (-2) on stray points and on clutter meshes. A fit reads label 1 as garment and anything
else as not garment; `diffavatar eval` scores only the label-1 points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from torch_diffavatar.errors import InputError
from torch_diffavatar.geometry import yaw_rotation
from torch_diffavatar.scan import UNITS, UP_AXES

FLOOR_LABEL = -1
STRAY_LABEL = -2
FLOOR_COLOR = (128, 124, 118)
# [m] a depth jump between neighbouring pixels beyond which a sensor may return a mixed depth (a silhouette)
FLYING_JUMP = 0.05
LAYOUTS = ("ring", "front")


@dataclass
class SceneMesh:
    """One labelled, uniformly coloured triangle mesh of the scene.

    Attributes:
        vertices: (V, 3) [m], world frame (Y up, floor at y = 0).
        faces: (F, 3) int vertex indices.
        label: the label of its points (1 garment, 0 skin, `STRAY_LABEL` clutter).
        color: RGB in 0..255.
    """

    vertices: np.ndarray
    faces: np.ndarray
    label: int
    color: tuple[int, int, int]


@dataclass(frozen=True)
class DepthCamera:
    """A pinhole depth camera looking from ``position`` at ``target`` (world frame [m]).

    Attributes:
        position, target: (3,) [m]. width, height: image size [px]. fov_y_deg: vertical field of view [deg].
    """

    position: tuple[float, float, float]
    target: tuple[float, float, float]
    width: int = 320
    height: int = 240
    fov_y_deg: float = 60.0

    def rotation(self) -> np.ndarray:
        """(3, 3) world → camera rotation, rows: right, down, forward (the OpenCV camera axes)."""
        forward = np.subtract(self.target, self.position).astype(np.float64)
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        return np.stack([right, np.cross(forward, right), forward])

    def focal(self) -> float:
        """Focal length [px] (square pixels)."""
        return 0.5 * self.height / math.tan(math.radians(0.5 * self.fov_y_deg))

    def rays(self) -> np.ndarray:
        """(H·W, 3) unit view rays of the pixel centres, world frame, row-major."""
        f = self.focal()
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        cam = np.stack(
            [(u.ravel() - 0.5 * (self.width - 1)) / f, (v.ravel() - 0.5 * (self.height - 1)) / f], 1
        )
        cam = np.concatenate([cam, np.ones((len(cam), 1))], 1)
        world = cam @ self.rotation()
        return world / np.linalg.norm(world, axis=1, keepdims=True)


def ring_cameras(
    count: int, centre: np.ndarray, *, distance: float = 2.2, camera_height: float = 1.1, **camera
) -> list[DepthCamera]:
    """``count`` cameras evenly around the vertical axis through ``centre`` (3,) [m], the first in front
    (+Z), at ``distance`` [m] from the axis and ``camera_height`` [m] above the floor, looking at ``centre``;
    ``camera``: `DepthCamera`'s image settings."""
    out = []
    for k in range(count):
        a = 2.0 * math.pi * k / count
        pos = (centre[0] + distance * math.sin(a), camera_height, centre[2] + distance * math.cos(a))
        out.append(DepthCamera(position=pos, target=tuple(float(c) for c in centre), **camera))
    return out


def front_camera(
    centre: np.ndarray, *, distance: float = 2.2, camera_height: float = 1.1, **camera
) -> DepthCamera:
    """One camera in front of the person (+Z); see `ring_cameras`."""
    return ring_cameras(1, centre, distance=distance, camera_height=camera_height, **camera)[0]


@dataclass(frozen=True)
class CaptureSettings:
    """How the simulated depth capture is made (see the module docstring).

    Attributes:
        layout: "ring" (``cameras`` around the person) or "front" (one camera in front).
        cameras: number of ring cameras.
        distance: horizontal camera distance from the person's vertical axis [m], in [1.5, 3].
        camera_height: height of the cameras above the floor [m].
        width, height: image size [px]. fov_y_deg: vertical field of view [deg].
        noise_a [m], noise_b [1/m]: depth noise sigma = noise_a + noise_b · d² at depth d [m].
        min_cos: returns with |cos(view ray, surface normal)| below this are dropped (grazing angles).
        color_noise: Gaussian noise of the colours [0..255 levels].
        stray_fraction: stray points added, as a fraction of the captured points.
        flying_pixels: the share of the pixels beside a depth jump of more than `FLYING_JUMP` that return
            a depth drawn uniformly between their own and their neighbour's (and the colours mixed alike),
            labelled as their own pixel [0, 1].
        calibration_m [m], calibration_deg [deg]: the standard deviations of each camera's pose error, a
            translation per axis and a rotation about a random axis through the camera: its points are
            placed by the registered pose while they were seen from the true one. Multi-camera rigs
            calibrated with a target are typically off by a few mm and a few tenths of a degree.
        floor_size: side of the square floor around the person [m] (0: no floor). The default 1 m puts
            about half the points on the floor (measured: 51 % with a ring of 4 at 640×480), as in the
            real captures of issue #29 (46 %).
        yaw_deg: turn of the whole capture about the vertical axis [deg].
        units: the output's length unit (`scan.UNITS`); up: the output's up axis (`scan.UP_AXES`).
    """

    layout: str = "ring"
    cameras: int = 4
    distance: float = 2.2
    camera_height: float = 1.1
    width: int = 640
    height: int = 480
    fov_y_deg: float = 60.0
    noise_a: float = 0.002
    noise_b: float = 0.0015
    min_cos: float = 0.15
    color_noise: float = 4.0
    stray_fraction: float = 0.002
    flying_pixels: float = 0.0
    calibration_m: float = 0.0
    calibration_deg: float = 0.0
    floor_size: float = 1.0
    yaw_deg: float = 0.0
    units: str = "m"
    up: str = "y"

    def check(self) -> None:
        """InputError naming the first setting out of its range."""
        if self.layout not in LAYOUTS:
            raise InputError(f"unknown capture layout {self.layout!r}; use one of {', '.join(LAYOUTS)}")
        if self.units not in UNITS or self.up not in UP_AXES:
            raise InputError(f"capture units must be one of {sorted(UNITS)} and up one of {sorted(UP_AXES)}")
        if not (isinstance(self.cameras, int) and 1 <= self.cameras <= 32):
            raise InputError(f"cameras must be an integer in [1, 32], got {self.cameras!r}")
        if not 1.5 <= self.distance <= 3.0:
            raise InputError(f"camera distance must lie in [1.5, 3] m, got {self.distance}")
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096 and 10.0 <= self.fov_y_deg <= 120.0):
            raise InputError("image size must be 16..4096 px and the field of view 10..120 degrees")
        for name in (
            "noise_a", "noise_b", "color_noise", "stray_fraction", "floor_size", "min_cos", "flying_pixels",
            "calibration_m", "calibration_deg",
        ):  # fmt: skip
            if not getattr(self, name) >= 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.min_cos >= 1 or self.stray_fraction > 0.5:
            raise InputError("need min_cos < 1 and stray_fraction <= 0.5")
        if self.flying_pixels > 1 or self.calibration_m > 0.1 or self.calibration_deg > 10:
            raise InputError("need flying_pixels <= 1, calibration_m <= 0.1 and calibration_deg <= 10")

    def camera_list(self, centre: np.ndarray) -> list[DepthCamera]:
        """The cameras around ``centre`` (3,) [m] (the person's centre)."""
        image = dict(width=self.width, height=self.height, fov_y_deg=self.fov_y_deg)
        count = self.cameras if self.layout == "ring" else 1
        return ring_cameras(count, centre, distance=self.distance, camera_height=self.camera_height, **image)


@dataclass
class CapturedScan:
    """A simulated capture, in the file's frame (``info["units"]``, ``info["up"]``).

    Attributes:
        points: (N, 3) float64 positions [the output units], the output axes.
        normals: (N, 3) float64 unit normals (towards the camera that saw the point), the output axes.
        colors: (N, 3) uint8 RGB.
        labels: (N,) int64: the meshes' labels, `FLOOR_LABEL`, `STRAY_LABEL`.
        info: settings and counts (yaw, units, up, cameras, noise, points per label).
    """

    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    labels: np.ndarray
    info: dict = field(default_factory=dict)


def to_file_frame(points: np.ndarray, units: str, up: str) -> np.ndarray:
    """World (Y up, metres) (N, 3) -> a file's frame: the inverse of `scan.load_scan`'s conversion."""
    return points @ UP_AXES[up] / UNITS[units]


def capture_scene(
    meshes: list[SceneMesh], settings: CaptureSettings, rng: np.random.Generator
) -> CapturedScan:
    """Capture ``meshes`` (world frame: Y up, metres, floor at y = 0) with depth cameras around the
    scene's centre, then yaw, scale and re-axis the result (see the module docstring).

    Args:
        meshes: the scene (a body, a garment, clutter), each a `SceneMesh`.
        settings: a `CaptureSettings`.
        rng: the source of every random draw.

    Returns:
        a `CapturedScan`.

    Raises:
        InputError: a setting out of range, or no mesh.
    """
    settings.check()
    if not meshes:
        raise InputError("capture_scene needs at least one mesh")
    allv = np.concatenate([np.asarray(m.vertices, np.float64) for m in meshes])
    lo, hi = allv.min(0), allv.max(0)
    centre = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2])])
    parts = [_capture_view(meshes, cam, settings, centre, rng) for cam in settings.camera_list(centre)]
    points, normals, colors, labels = (np.concatenate([p[k] for p in parts]) for k in range(4))
    points, normals, colors, labels = _add_strays(points, normals, colors, labels, lo, hi, settings, rng)
    rot = yaw_rotation(settings.yaw_deg)
    points, normals = points @ rot.T, normals @ rot.T
    info = _capture_info(settings, labels)
    return CapturedScan(
        points=to_file_frame(points, settings.units, settings.up),
        normals=normals @ UP_AXES[settings.up],
        colors=colors,
        labels=labels,
        info=info,
    )


def _capture_view(meshes, cam: DepthCamera, s: CaptureSettings, centre: np.ndarray, rng) -> tuple:
    """One camera's points (P, 3) [m], normals (P, 3), colours (P, 3) uint8 and labels (P,), world frame."""
    verts = np.concatenate([np.asarray(m.vertices, np.float64) for m in meshes])
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
    tris = np.concatenate([np.asarray(m.faces, np.int64) + o for m, o in zip(meshes, offsets)])
    tri_mesh = np.repeat(np.arange(len(meshes)), [len(m.faces) for m in meshes])
    depth, tri = rasterize(cam, verts, tris)  # (H·W,) depth along the optical axis [m], triangle or -1
    rays = cam.rays()
    forward = cam.rotation()[2]
    along = rays @ forward  # (H·W,) cos of each ray to the optical axis: distance = depth / along
    dist = np.where(tri >= 0, depth / along, np.inf)
    tri_normal = np.cross(verts[tris[:, 1]] - verts[tris[:, 0]], verts[tris[:, 2]] - verts[tris[:, 0]])
    tri_normal /= np.maximum(np.linalg.norm(tri_normal, axis=1, keepdims=True), 1e-20)
    normal = np.zeros_like(rays)
    normal[tri >= 0] = tri_normal[tri[tri >= 0]]
    label = np.full(len(rays), FLOOR_LABEL, np.int64)
    color = np.tile(np.array(FLOOR_COLOR, np.float64), (len(rays), 1))
    hit = tri >= 0
    mesh_of_hit = tri_mesh[tri[hit]]
    label[hit] = np.array([m.label for m in meshes], np.int64)[mesh_of_hit]
    color[hit] = np.array([m.color for m in meshes], np.float64)[mesh_of_hit]
    if s.floor_size > 0:  # the floor y = 0, where nothing nearer covers it
        pos = np.asarray(cam.position, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -pos[1] / rays[:, 1]
        on = np.isfinite(t) & (t > 0)
        foot = pos + np.where(on, t, 0.0)[:, None] * rays
        half = 0.5 * s.floor_size
        on &= (np.abs(foot[:, 0] - centre[0]) <= half) & (np.abs(foot[:, 2] - centre[2]) <= half) & (t < dist)
        dist[on], normal[on], label[on], color[on] = t[on], (0.0, 1.0, 0.0), FLOOR_LABEL, FLOOR_COLOR
    if s.flying_pixels > 0:
        dist, color = _mixed_pixels(dist, color, cam, s.flying_pixels, rng)
    seen = np.isfinite(dist)
    cos = np.abs((normal * rays).sum(1))
    keep = seen & (cos >= s.min_cos)
    depth_k = dist[keep] * along[keep]
    sigma = s.noise_a + s.noise_b * depth_k**2
    noisy = dist[keep] + rng.normal(0.0, 1.0, len(depth_k)) * sigma / along[keep]
    points = np.asarray(cam.position, np.float64) + noisy[:, None] * rays[keep]
    facing_away = (normal[keep] * rays[keep]).sum(1, keepdims=True) > 0
    normals = np.where(facing_away, -normal[keep], normal[keep])  # towards the camera
    colors = np.clip(color[keep] + rng.normal(0.0, s.color_noise, (len(points), 3)), 0, 255).astype(np.uint8)
    if s.calibration_m > 0 or s.calibration_deg > 0:  # placed by the registered pose, seen from the true one
        rot, shift = _pose_error(s, rng)
        pos = np.asarray(cam.position, np.float64)
        points, normals = (points - pos) @ rot.T + pos + shift, normals @ rot.T
    return points, normals, colors, label[keep]


def _mixed_pixels(dist: np.ndarray, color: np.ndarray, cam: DepthCamera, share: float, rng) -> tuple:
    """(H·W,) distances along the rays [m] and (H·W, 3) colours with ``share`` of the pixels beside a depth
    jump (> `FLYING_JUMP`, both sides seen) moved a uniform fraction of the way to their neighbour's
    distance, the colour mixed alike (a pixel beside several jumps mixes with the first found)."""
    idx = np.arange(dist.size).reshape(cam.height, cam.width)
    d = dist.reshape(cam.height, cam.width)
    pairs = []
    for dy, dx in ((0, 1), (1, 0)):
        a, b = d[: d.shape[0] - dy, : d.shape[1] - dx], d[dy:, dx:]
        with np.errstate(invalid="ignore"):  # inf - inf where neither sees anything
            jump = np.isfinite(a) & np.isfinite(b) & (np.abs(a - b) > FLYING_JUMP)
        p, q = idx[: d.shape[0] - dy, : d.shape[1] - dx][jump], idx[dy:, dx:][jump]
        pairs += [np.stack([p, q], 1), np.stack([q, p], 1)]
    pairs = np.concatenate(pairs)
    pairs = pairs[np.unique(pairs[:, 0], return_index=True)[1]]
    pairs = pairs[rng.random(len(pairs)) < share]
    u = rng.random(len(pairs))
    dist, color = dist.copy(), color.copy()
    p, q = pairs[:, 0], pairs[:, 1]
    dist[p] = dist[p] + u * (dist[q] - dist[p])
    color[p] = (1.0 - u)[:, None] * color[p] + u[:, None] * color[q]
    return dist, color


def _pose_error(s: CaptureSettings, rng) -> tuple[np.ndarray, np.ndarray]:
    """A camera's pose error: (3, 3) rotation (a normal angle of ``calibration_deg`` about a random axis)
    and (3,) translation (normal, ``calibration_m`` per axis) [m]."""
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=3)
    axis /= max(float(np.linalg.norm(axis)), 1e-12)
    angle = math.radians(float(rng.normal(0.0, s.calibration_deg)))
    return Rotation.from_rotvec(angle * axis).as_matrix(), rng.normal(0.0, s.calibration_m, 3)


def rasterize(cam: DepthCamera, verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer of a triangle mesh seen by ``cam`` (the rasteriser of `render`, with perspective-correct
    depth: 1/z is affine in screen space).

    Args:
        cam: the `DepthCamera`. verts: (V, 3) [m] world frame. faces: (F, 3) int.

    Returns:
        depth: (H·W,) float64 depth along the optical axis [m] of the nearest surface at each pixel
        centre (inf where none); tri: (H·W,) int64 its triangle (-1 where none). Row-major pixels.
        Triangles with a vertex closer than 5 cm to the camera plane are skipped (none in a capture).
    """
    from torch_diffavatar.render import _rasterize

    cam_pts = (verts - np.asarray(cam.position)) @ cam.rotation().T  # (V, 3) camera frame
    z = cam_pts[:, 2]
    f = cam.focal()
    # `render` puts pixel centres at +0.5; ours (`DepthCamera.rays`) at the integers
    pix = np.stack([f * cam_pts[:, 0] / z + 0.5 * cam.width, f * cam_pts[:, 1] / z + 0.5 * cam.height], 1)
    ok = np.flatnonzero((z[faces] > 0.05).all(1))
    tri, bary = _rasterize(pix, -1.0 / np.maximum(z, 0.05), faces[ok], cam.width, cam.height)
    hit = tri >= 0
    depth = np.full(len(tri), np.inf)
    depth[hit] = 1.0 / (bary[hit] / z[faces[ok][tri[hit]]]).sum(1)
    return depth, np.where(hit, ok[np.maximum(tri, 0)], -1)


def _add_strays(points, normals, colors, labels, lo, hi, s: CaptureSettings, rng):
    """Append ``stray_fraction`` × N uniform points in the scene's box grown by 0.5 m (above the floor),
    with random normals and colours, labelled `STRAY_LABEL`."""
    count = int(round(s.stray_fraction * len(points)))
    box_lo = np.array([lo[0] - 0.5, 0.0, lo[2] - 0.5])
    box_hi = np.array([hi[0] + 0.5, hi[1] + 0.5, hi[2] + 0.5])
    pts = box_lo + rng.random((count, 3)) * (box_hi - box_lo)
    nrm = rng.normal(size=(count, 3))
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    col = rng.integers(0, 256, (count, 3)).astype(np.uint8)
    return (
        np.concatenate([points, pts]),
        np.concatenate([normals, nrm]),
        np.concatenate([colors, col]),
        np.concatenate([labels, np.full(count, STRAY_LABEL, np.int64)]),
    )


def _capture_info(s: CaptureSettings, labels: np.ndarray) -> dict:
    """The settings and the point counts by label (``truth.json``'s ``capture``)."""
    names = {1: "garment", 0: "skin", FLOOR_LABEL: "floor", STRAY_LABEL: "stray"}
    return {
        "layout": s.layout,
        "cameras": s.cameras if s.layout == "ring" else 1,
        "camera_distance_m": s.distance,
        "camera_height_m": s.camera_height,
        "image_px": [s.width, s.height],
        "fov_y_deg": s.fov_y_deg,
        "depth_noise_m": {"a": s.noise_a, "b_per_m2": s.noise_b, "sigma": "a + b * depth^2"},
        "min_cos": s.min_cos,
        "flying_pixels": s.flying_pixels,
        "calibration_error": {"translation_m": s.calibration_m, "rotation_deg": s.calibration_deg},
        "yaw_deg": s.yaw_deg,
        "units": s.units,
        "up": s.up,
        "labels": {"garment": 1, "skin": 0, "floor": FLOOR_LABEL, "stray": STRAY_LABEL},
        "points": {names.get(int(k), str(int(k))): int((labels == k).sum()) for k in np.unique(labels)},
    }
