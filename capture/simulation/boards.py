"""Calibration images rendered by Mitsuba: a ChArUco board held in front of the rig's cameras.

The board is a Mitsuba ``rectangle`` carrying the board's picture as a ``bitmap``
texture. Each camera's pixels are sampled (stratified, box filter) and their rays
built by :meth:`mifacerf.camera.Camera.pixel_rays` — the same lens model
calibration has to recover — then traced with ``scene.ray_intersect``; the texture
is evaluated at the hit's ``si.uv``. So the images carry exactly the intrinsics,
distortion and poses of the given cameras and board poses (the ground truth).

Board poses are rigid transforms board -> **world**: ``x_world = R @ x_board + t``
(board frame: :mod:`mifacerf.capture.calibration.charuco`). :func:`board_poses`
draws a seeded set about a centre, facing the cameras, the first one exactly facing +Z
(:func:`facing_pose`) so it can anchor the world; :func:`write_board_dataset` centres
them where the cameras' optical axes meet (:func:`cameras_focus`).
"""
from __future__ import annotations

import numpy as np

from ...camera import Camera, cameras_focus, stratified_pixel_samples
from ...variant import ensure_variant
from ..calibration.charuco import BoardSpec


def rotation(axis, angle: float) -> np.ndarray:
    """Rotation matrix about unit ``axis`` by ``angle`` radians (Rodrigues)."""
    import cv2

    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    return cv2.Rodrigues(a * angle)[0]


def facing_pose(board: BoardSpec, centre=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """The board upright at ``centre``, its printed face towards +Z (the cameras):
    board +x -> world +X, board +y (down) -> world -Y, board +z -> world -Z."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    w, h = board.size
    t = np.asarray(centre, np.float64) - R @ np.array([w / 2, h / 2, 0.0])
    return R, t


def board_poses(board: BoardSpec, n: int = 12, seed: int = 0, tilt_deg: float = 35.0, roll_deg: float = 20.0,
                offset: float = 0.04, depth: float = 0.15,
                centre=(0.0, 0.0, 0.04)) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` board poses (R, t), board -> world: the first :func:`facing_pose` at ``centre``, the
    rest tilted up to ``tilt_deg`` about X and Y, rolled up to ``roll_deg``, moved up to
    ``offset`` metres sideways and ``depth`` metres towards or away from the cameras about
    ``centre``. The depth changes matter: with narrow zoom lenses they are what separates a
    camera's focal length from its distance."""
    rng = np.random.default_rng(seed)
    out = [facing_pose(board, centre)]
    w, h = board.size
    R0, _ = facing_pose(board)
    for i in range(1, n):
        # alternate strong tilts about the two axes so every camera sees foreshortening both ways
        ax = np.radians(tilt_deg) * (rng.uniform(0.4, 1.0) * rng.choice([-1, 1]))
        ay = np.radians(tilt_deg) * (rng.uniform(0.4, 1.0) * rng.choice([-1, 1]))
        if i % 3 == 1:
            ay *= 0.3
        elif i % 3 == 2:
            ax *= 0.3
        az = np.radians(roll_deg) * rng.uniform(-1, 1)
        R = rotation([0, 1, 0], ay) @ rotation([1, 0, 0], ax) @ rotation([0, 0, 1], az) @ R0
        c = np.asarray(centre) + np.r_[offset * rng.uniform(-1, 1, 2), depth * rng.uniform(-1, 1)]
        t = c - R @ np.array([w / 2, h / 2, 0.0])
        out.append((R, t))
    return out


class BoardRenderer:
    """Renders ``board`` (``px_per_square`` texture resolution) into cameras with ``spp`` samples."""

    def __init__(self, board: BoardSpec, spp: int = 4, px_per_square: int = 64, seed: int = 0,
                 black: float = 0.05, white: float = 0.85, background: float = 0.35, noise: float = 0.004):
        self.board, self.spp, self.seed = board, int(spp), seed
        self.black, self.white, self.background, self.noise = black, white, background, noise
        img = board.image(px_per_square).astype(np.float32) / 255.0
        self.texture_image = np.repeat(img[..., None], 3, axis=2)
        self._rays: dict[str, object] = {}

    def _scene(self, R: np.ndarray, t: np.ndarray):
        mi = ensure_variant()
        w, h = self.board.size
        # rectangle local [-1, 1]^2, uv = ((x + 1) / 2, (y + 1) / 2); bitmap row 0 at v = 0 = board's top edge
        local_to_board = np.array([[w / 2, 0, 0, w / 2], [0, h / 2, 0, h / 2], [0, 0, 1, 0], [0, 0, 0, 1]])
        board_to_world = np.eye(4)
        board_to_world[:3, :3], board_to_world[:3, 3] = R, t
        scene = mi.load_dict({"type": "scene", "board": {
            "type": "rectangle", "to_world": mi.ScalarTransform4f(board_to_world @ local_to_board)}})
        return scene

    def texture(self):
        mi = ensure_variant()
        if not hasattr(self, "_texture"):
            self._texture = mi.load_dict({"type": "bitmap", "bitmap": mi.Bitmap(self.texture_image), "raw": True,
                                          "filter_type": "bilinear", "wrap_mode": "clamp"})
        return self._texture

    def _camera_rays(self, camera: Camera):
        key = camera.name + repr((camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(),
                                  camera.R.tobytes(), camera.t.tobytes()))
        if key not in self._rays:
            mi = ensure_variant()
            uv = stratified_pixel_samples(camera.width, camera.height, self.spp, self.seed)
            o, d = camera.pixel_rays(uv)
            origin = mi.Point3f(*[mi.Float(np.full(len(d), o[i], np.float32)) for i in range(3)])
            self._rays = {key: mi.Ray3f(origin, mi.Vector3f(np.ascontiguousarray(d.T, dtype=np.float32)))}
        return self._rays[key]

    def render(self, camera: Camera, pose: tuple[np.ndarray, np.ndarray], seed: int = 0) -> np.ndarray:
        """(H, W) float32 grey image of the board at ``pose`` (board -> world) seen by ``camera``."""
        scene = self._scene(*pose)
        ray = self._camera_rays(camera)
        si = scene.ray_intersect(ray)
        valid = np.asarray(si.is_valid()).astype(bool)
        albedo = np.asarray(self.texture().eval(si))
        albedo = (albedo[0] if albedo.shape[0] == 3 else albedo[:, 0]).astype(np.float64)
        value = np.where(valid, self.black + (self.white - self.black) * albedo, self.background)
        img = value.reshape(camera.height, camera.width, self.spp).mean(axis=2)
        if self.noise:
            img = img + self.noise * np.random.default_rng(seed).standard_normal(img.shape)
        return np.clip(img, 0, 1).astype(np.float32)

    def render_views(self, cameras: list[Camera], poses, log=None) -> dict[str, list[np.ndarray]]:
        """Images per camera name, one per pose (camera-major order, so rays are traced once per camera);
        ``log(camera name)`` after each camera."""
        out = {}
        for ci, cam in enumerate(cameras):
            out[cam.name] = [self.render(cam, p, seed=1000 * ci + vi) for vi, p in enumerate(poses)]
            if log:
                log(cam.name)
        return out


def write_board_dataset(root, cameras: list[Camera], board: BoardSpec, *, n_views: int = 20, spp: int = 4,
                        tilt_deg: float = 55.0, seed: int = 0, log=None):
    """Render ``n_views`` board poses into every camera and write a board-capture folder:
    ``boards.json`` (board, views, the world pose of view 0), ``<camera>/V<view>.png`` (8-bit
    grey) and ``truth.json`` (the cameras and board poses used); ``log(camera name)`` after each camera."""
    import json
    from pathlib import Path

    from ...formats.files import write_json_atomic
    from ...imageio import write_png

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    poses = board_poses(board, n_views, seed=seed, tilt_deg=tilt_deg, centre=cameras_focus(cameras))
    renderer = BoardRenderer(board, spp=spp, seed=seed)
    for ci, cam in enumerate(cameras):
        (root / cam.name).mkdir(exist_ok=True)
        for vi, pose in enumerate(poses):
            img = renderer.render(cam, pose, seed=1000 * ci + vi)
            write_png(root / cam.name / f"V{vi:03d}.png", (img * 255 + 0.5).astype(np.uint8))
        if log:
            log(cam.name)
    write_json_atomic(root / "boards.json", {
        "format": "mifacerf.board-captures", "version": 1, "board": board.to_dict(),
        "cameras": [c.name for c in cameras], "views": n_views, "pattern": "{camera}/V{view:03d}.png",
        "world_view": 0, "world_pose": {"R": poses[0][0].tolist(), "t": poses[0][1].tolist()}})
    (root / "truth.json").write_text(json.dumps({
        "cameras": [c.to_dict() for c in cameras],
        "board_poses": [{"R": R.tolist(), "t": t.tolist()} for R, t in poses]}, indent=1))
    return root


def read_board_dataset(root) -> tuple[BoardSpec, dict[str, list[np.ndarray]], dict]:
    """(board, {camera: [grey uint8 image or None per view]}, description) of a board-capture folder."""
    import json
    from pathlib import Path

    import cv2

    root = Path(root)
    p = root / "boards.json"
    if not p.exists():
        raise FileNotFoundError(f"{p}: missing; not a board-capture folder")
    desc = json.loads(p.read_text())
    board = BoardSpec.from_dict(desc["board"])
    images = {}
    for cam in desc["cameras"]:
        imgs = []
        for v in range(desc["views"]):
            f = root / desc["pattern"].format(camera=cam, view=v)
            imgs.append(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) if f.exists() else None)
        images[cam] = imgs
    return board, images, desc
