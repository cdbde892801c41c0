"""Geometric calibration of the rig's cameras by Zhang's method (paper §2.1, [Zha00]).

Each camera is calibrated on its own from planar-board views (``cv2.calibrateCamera``
on ChArUco corners, OpenCV distortion ``(k1, k2, p1, p2, k3)``), with outlier corners
(reprojection error above ``max(3 x median, 1 px)``) dropped and the fit repeated.
Then all cameras and all board poses are refined together (bundle adjustment,
``scipy.optimize.least_squares``, robust loss), which also gives the cameras'
relative poses from the views two cameras share.

World frame: when the world pose of one board view is known (``world_view`` with
``world_pose``, e.g. the board held upright at the stage centre facing the cameras,
:func:`mifacerf.capture.simulation.boards.facing_pose`), the rig is placed in
**world**; otherwise camera ``reference`` is the world frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...camera import Camera
from .charuco import BoardSpec, Detection, detect
from ...errors import MifacerfError


class CalibrationError(MifacerfError, RuntimeError):
    """Too few usable views, a camera that never saw the board, or a fit that failed."""


@dataclass
class CameraCalibration:
    """One camera: its :class:`~mifacerf.camera.Camera`, RMS reprojection errors (pixels)
    before and after the joint refinement, the views used and the corners kept."""

    camera: Camera
    rms_single: float
    rms: float
    views: list[int]
    corners: int
    outliers: int

    def to_dict(self) -> dict:
        return {"camera": self.camera.to_dict(), "rms_single_px": self.rms_single, "rms_px": self.rms,
                "views": self.views, "corners": self.corners, "outliers": self.outliers}


@dataclass
class RigCalibration:
    cameras: list[CameraCalibration]
    board: BoardSpec
    board_poses: dict[int, tuple[np.ndarray, np.ndarray]]  # view -> (R, t) board -> world
    world: str
    rms: float
    extra: dict = field(default_factory=dict)

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.camera.name == name:
                return c.camera
        raise KeyError(name)

    def to_dict(self) -> dict:
        return {"format": "mifacerf.geometric-calibration", "version": 1, "method": "zhang2000",
                "board": self.board.to_dict(), "world": self.world, "rms_px": self.rms,
                "cameras": [c.to_dict() for c in self.cameras],
                "board_poses": {str(v): {"R": R.tolist(), "t": t.tolist()} for v, (R, t) in self.board_poses.items()},
                **self.extra}


def _rt_to_T(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.asarray(t).reshape(3)
    return T


def _rvec(R) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(R, np.float64))[0].reshape(3)


def _R(rvec) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]


def rodrigues(r: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) -> rotation matrices (N, 3, 3), vectorised."""
    r = np.asarray(r, np.float64).reshape(-1, 3)
    th = np.linalg.norm(r, axis=1)
    k = r / np.where(th > 1e-12, th, 1.0)[:, None]
    Kx = np.zeros((len(r), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx -= Kx.transpose(0, 2, 1)
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3)[None] + s * Kx + (1 - c) * Kx @ Kx


def distort_project(Xc: np.ndarray, intr: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) -> pixels (N, 2) with per-point intrinsics (N, 9):
    fx, fy, cx, cy, k1, k2, p1, p2, k3 (OpenCV model, as :meth:`mifacerf.camera.Camera.project`)."""
    x, y = Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2]
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intr.T
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fx * xd + cx, fy * yd + cy], axis=1)


def mean_rotation(Rs) -> np.ndarray:
    """Chordal L2 mean of rotation matrices (SVD projection of their sum)."""
    U, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


#: Distortion models: which of (k1, k2, p1, p2, k3) are estimated (the rest stay 0).
DISTORTION_MODELS = {
    "full": (True, True, True, True, False),
    "radial": (True, True, False, False, False),
    "k1": (True, False, False, False, False),
    "none": (False, False, False, False, False),
}


def _model_flags(model: str, fix_principal_point: bool = False) -> int:
    import cv2

    try:
        k1, k2, p, _, k3 = DISTORTION_MODELS[model]
    except KeyError:
        raise ValueError(f"unknown distortion model {model!r}; choose one of {', '.join(DISTORTION_MODELS)}") from None
    flags = 0
    if not k1:
        flags |= cv2.CALIB_FIX_K1
    if not k2:
        flags |= cv2.CALIB_FIX_K2
    if not p:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    if not k3:
        flags |= cv2.CALIB_FIX_K3
    if fix_principal_point:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    return flags


def calibrate_single(detections: dict[int, Detection], width: int, height: int, *, model: str = "full",
                     fix_principal_point: bool = False, square_pixels: bool = False, name: str = "camera",
                     max_iter: int = 3):
    """Zhang's calibration of one camera from ``detections`` {view: Detection}.

    Returns ``(K, dist, {view: (R, t) board -> camera}, rms, n_corners, n_outliers, kept)``
    with ``kept`` {view: bool mask of the corners used}.
    """
    import cv2

    views = sorted(v for v, d in detections.items() if d is not None and len(d) >= 6)
    if len(views) < 3:
        raise CalibrationError(f"{name}: the board was found in {len(views)} view(s); Zhang's method needs >= 3 "
                               "(ideally 10-15 at varied tilts)")
    keep = {v: np.ones(len(detections[v]), bool) for v in views}
    flags = _model_flags(model, fix_principal_point) | (cv2.CALIB_FIX_ASPECT_RATIO if square_pixels else 0)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    outliers = 0
    K = dist = rvecs = tvecs = None
    rms = np.inf
    for it in range(max_iter + 1):
        used = [v for v in views if keep[v].sum() >= 6]
        if len(used) < 3:
            raise CalibrationError(f"{name}: only {len(used)} view(s) keep >= 6 consistent corners")
        obj = [detections[v].object_points[keep[v]].astype(np.float32) for v in used]
        img = [detections[v].image_points[keep[v]].astype(np.float32) for v in used]
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, (width, height), None, None, flags=flags,
                                                         criteria=crit)
        if it == max_iter:
            break
        # drop corners far off the fit (mis-detections), then fit again
        errs = {}
        for v, rv, tv in zip(used, rvecs, tvecs):
            d = detections[v]
            proj, _ = cv2.projectPoints(d.object_points, rv, tv, K, dist)
            errs[v] = np.linalg.norm(proj.reshape(-1, 2) - d.image_points, axis=1)
        limit = max(3 * np.median(np.concatenate([errs[v][keep[v]] for v in used])), 1.0)
        new_keep = {v: (errs[v] <= limit) if v in errs else np.zeros_like(keep[v]) for v in views}
        if all(np.array_equal(new_keep[v], keep[v]) for v in views):
            break
        keep = new_keep
    keep = {v: keep[v] for v in used}
    outliers = int(sum(len(detections[v]) - keep[v].sum() for v in used))
    poses = {v: (_R(rv), np.asarray(tv, np.float64).reshape(3)) for v, rv, tv in zip(used, rvecs, tvecs)}
    n = int(sum(keep[v].sum() for v in used))
    return K, np.asarray(dist, np.float64).reshape(-1)[:5], poses, float(rms), n, outliers, keep


def detect_views(board: BoardSpec, images: dict[str, list[np.ndarray]]) -> dict[str, dict[int, Detection]]:
    """ChArUco detections per camera name and view index (views without the board are left out)."""
    out = {}
    for cam, imgs in images.items():
        out[cam] = {}
        for v, img in enumerate(imgs):
            if img is None:
                continue
            d = detect(board, img)
            if d is not None:
                out[cam][v] = d
    return out


def calibrate_rig(board: BoardSpec, detections: dict[str, dict[int, Detection]], sizes: dict[str, tuple[int, int]],
                  *, model: str = "full", reference: str | None = None, world_view: int | None = None,
                  world_pose: tuple[np.ndarray, np.ndarray] | None = None, refine: bool = True,
                  square_pixels: bool = True, principal_prior_px: float | None = None,
                  loss: str = "linear", noise_px: float = 0.25) -> RigCalibration:
    """Calibrate every camera and their poses from ChArUco ``detections`` {camera: {view: Detection}}.

    ``sizes``: {camera: (width, height)}; ``model``: distortion terms estimated
    (:data:`DISTORTION_MODELS`); ``square_pixels``: one focal length (fx = fy), true of
    every modern sensor. The cameras must be connected through shared views.

    1. Zhang per camera with a robust model (k1 only, principal point at the image
       centre): narrow zoom lenses leave the principal point and higher distortion
       terms nearly unobservable from one camera's views alone.
    2. Relative poses chained through shared views; board poses averaged over cameras.
    3. Bundle adjustment of everything with the full ``model`` and free principal
       points: a board seen by cameras 80 degrees apart fixes its pose, which in turn
       pins every camera's focal length and principal point.
    """
    import cv2
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    names = list(detections)
    if not names:
        raise CalibrationError("no cameras to calibrate")
    free = np.array([True, not square_pixels, True, True, *DISTORTION_MODELS[model]]) \
        if model in DISTORTION_MODELS else None
    if free is None:
        raise ValueError(f"unknown distortion model {model!r}; choose one of {', '.join(DISTORTION_MODELS)}")
    single = {}
    for c in names:
        w, h = sizes[c]
        single[c] = calibrate_single(detections[c], w, h, model="k1" if refine else model,
                                     fix_principal_point=refine, square_pixels=square_pixels, name=c)
    reference = reference or names[0]
    # --- initial rig: camera poses relative to the reference camera, chained through shared views
    cam_T = {reference: np.eye(4)}  # reference-camera frame -> camera
    pending = [c for c in names if c != reference]
    while pending:
        progress = False
        for c in list(pending):
            Rs, ts = [], []
            for known in list(cam_T):
                for v in set(single[c][2]) & set(single[known][2]):
                    T = _rt_to_T(*single[c][2][v]) @ np.linalg.inv(_rt_to_T(*single[known][2][v])) @ cam_T[known]
                    Rs.append(T[:3, :3])
                    ts.append(T[:3, 3])
            if Rs:
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = mean_rotation(Rs), np.median(ts, axis=0)
                cam_T[c] = T
                pending.remove(c)
                progress = True
        if not progress:
            raise CalibrationError(f"cameras {pending} share no board view with {reference} (nor with cameras "
                                   "linked to it); hold the board where they see it together with another camera")
    views = sorted({v for c in names for v in single[c][2]})
    board_T = {}
    for v in views:
        Rs, ts = [], []
        for c in names:
            if v in single[c][2]:
                T = np.linalg.inv(cam_T[c]) @ _rt_to_T(*single[c][2][v])  # board -> reference frame
                Rs.append(T[:3, :3])
                ts.append(T[:3, 3])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = mean_rotation(Rs), np.median(ts, axis=0)
        board_T[v] = T

    # --- bundle adjustment: per camera 9 intrinsics (masked by the model) + 6 pose, per view 6 pose
    obs = []  # (camera index, view index, object points, image points)
    vi = {v: i for i, v in enumerate(views)}
    for ci, c in enumerate(names):
        keep = single[c][6]
        for v, d in detections[c].items():
            if v in keep:
                obs.append((ci, vi[v], d.object_points[keep[v]], d.image_points[keep[v]]))
    n_c, n_v = len(names), len(views)
    intr0 = np.array([[single[c][0][0, 0], single[c][0][1, 1], single[c][0][0, 2], single[c][0][1, 2],
                       *single[c][1][:5]] for c in names])
    n_free = int(free.sum())
    ref_i = names.index(reference)
    # parameters: free intrinsics (n_c x n_free), camera poses except the reference ((n_c-1) x 6), boards (n_v x 6)
    cam_order = [i for i in range(n_c) if i != ref_i]

    def pack():
        x = [intr0[:, free].ravel()]
        x += [np.r_[_rvec(cam_T[names[i]][:3, :3]), cam_T[names[i]][:3, 3]] for i in cam_order]
        x += [np.r_[_rvec(board_T[v][:3, :3]), board_T[v][:3, 3]] for v in views]
        return np.concatenate(x)

    def unpack(x):
        intr = intr0.copy()
        intr[:, free] = x[:n_c * n_free].reshape(n_c, n_free)
        if square_pixels:
            intr[:, 1] = intr[:, 0]
        cams = np.zeros((n_c, 6))
        cams[ref_i] = np.r_[_rvec(np.eye(3)), np.zeros(3)]
        off = n_c * n_free
        cams[cam_order] = x[off:off + 6 * (n_c - 1)].reshape(n_c - 1, 6)
        boards = x[off + 6 * (n_c - 1):].reshape(n_v, 6)
        return intr, cams, boards

    # all observations flattened: per point its camera, its board view, object and image coordinates
    P_cam = np.concatenate([np.full(len(op), ci) for ci, _, op, _ in obs])
    P_board = np.concatenate([np.full(len(op), bi) for _, bi, op, _ in obs])
    P_obj = np.concatenate([op for _, _, op, _ in obs])
    P_img = np.concatenate([ip for _, _, _, ip in obs])

    def residuals(x):
        intr, cams, boards = unpack(x)
        Rb, Rc = rodrigues(boards[:, :3]), rodrigues(cams[:, :3])
        Xw = np.einsum("nij,nj->ni", Rb[P_board], P_obj) + boards[P_board, 3:]
        Xc = np.einsum("nij,nj->ni", Rc[P_cam], Xw) + cams[P_cam, 3:]
        uv = distort_project(Xc, intr[P_cam])
        res = (uv - P_img).ravel()
        if principal_prior_px:
            centre = np.array([[(sizes[c][0] - 1) / 2, (sizes[c][1] - 1) / 2] for c in names])
            res = np.concatenate([res, ((intr[:, 2:4] - centre) * (noise_px / principal_prior_px)).ravel()])
        return res

    x0 = pack()
    x = x0
    if refine:
        n_res = sum(2 * len(op) for _, _, op, _ in obs)
        sparsity = lil_matrix((n_res, len(x0)), dtype=int)
        row = 0
        off_cam = n_c * n_free
        off_board = off_cam + 6 * (n_c - 1)
        for ci, bi, op, _ in obs:
            rows = slice(row, row + 2 * len(op))
            sparsity[rows, ci * n_free:(ci + 1) * n_free] = 1
            if ci != ref_i:
                k = cam_order.index(ci)
                sparsity[rows, off_cam + 6 * k:off_cam + 6 * (k + 1)] = 1
            sparsity[rows, off_board + 6 * bi:off_board + 6 * (bi + 1)] = 1
            row += 2 * len(op)
        if principal_prior_px:
            sparsity.resize((n_res + 2 * n_c, len(x0)))
            for ci in range(n_c):
                sparsity[n_res + 2 * ci:n_res + 2 * ci + 2, ci * n_free:(ci + 1) * n_free] = 1
        from scipy.optimize._numdiff import approx_derivative, group_columns

        sparsity = sparsity.tocsc()
        groups = group_columns(sparsity)

        def jac(x):  # finite differences over groups of independent columns, dense for the exact solver
            J = approx_derivative(residuals, x, sparsity=(sparsity, groups))
            return J.toarray()

        if loss == "linear":  # Levenberg-Marquardt (MINPACK): few iterations on this small dense problem
            sol = least_squares(residuals, x0, jac=jac, method="lm", x_scale="jac", max_nfev=200)
        else:
            sol = least_squares(residuals, x0, jac=jac, loss=loss, f_scale=2 * noise_px, x_scale="jac",
                                tr_solver="exact", max_nfev=100)
        if sol.status < 0:
            raise CalibrationError(f"bundle adjustment failed: {sol.message}")
        x = sol.x
    intr, cams, boards = unpack(x)
    res = residuals(x)[:len(P_img) * 2].reshape(-1, 2)

    # --- world frame
    world = f"camera {reference}"
    W = np.eye(4)  # reference-camera frame -> world
    if world_view is not None and world_pose is not None:
        if world_view not in vi:
            raise CalibrationError(f"world view {world_view} was not detected by any camera")
        b = boards[vi[world_view]]
        W = _rt_to_T(*world_pose) @ np.linalg.inv(_rt_to_T(_R(b[:3]), b[3:]))
        world = f"world (board view {world_view} at its known pose)"
    Winv = np.linalg.inv(W)
    per_cam: dict[int, list[np.ndarray]] = {i: [] for i in range(n_c)}
    k = 0
    for ci, bi, op, _ in obs:
        per_cam[ci].append(res[k:k + len(op)])
        k += len(op)
    out = []
    for ci, c in enumerate(names):
        fx, fy, cx, cy = intr[ci, :4]
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        T = _rt_to_T(_R(cams[ci, :3]), cams[ci, 3:]) @ Winv  # world -> camera
        U, _, Vt = np.linalg.svd(T[:3, :3])
        w, h = sizes[c]
        cam = Camera(c, w, h, K, intr[ci, 4:], U @ Vt, T[:3, 3])
        r = np.concatenate(per_cam[ci])
        out.append(CameraCalibration(cam, single[c][3], float(np.sqrt((r ** 2).sum(axis=1).mean())),
                                     sorted(single[c][2]), single[c][4], single[c][5]))
    poses = {}
    for v in views:
        T = W @ _rt_to_T(_R(boards[vi[v], :3]), boards[vi[v], 3:])
        poses[v] = (T[:3, :3], T[:3, 3])
    rms = float(np.sqrt((res ** 2).sum(axis=1).mean()))
    return RigCalibration(out, board, poses, world, rms, {"model": model, "views": len(views)})


def pose_errors(estimated: Camera, truth: Camera) -> dict:
    """Rotation error (degrees), camera-centre error (metres), focal error (relative), principal-point error (px)."""
    dR = estimated.R @ truth.R.T
    ang = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    return {"rotation_deg": float(ang), "centre_m": float(np.linalg.norm(estimated.centre - truth.centre)),
            "focal_rel": float(np.mean([abs(estimated.K[0, 0] / truth.K[0, 0] - 1),
                                        abs(estimated.K[1, 1] / truth.K[1, 1] - 1)])),
            "principal_px": float(np.linalg.norm(estimated.K[:2, 2] - truth.K[:2, 2])),
            "dist_abs": (np.abs(estimated.dist - truth.dist)).tolist(),
            "distortion_px": distortion_difference_px(estimated, truth)}


def distortion_difference_px(estimated: Camera, truth: Camera, n: int = 21) -> float:
    """Largest difference (pixels, at the true focal length) between the two lens distortions over
    the true camera's image: how far apart the two models put the same ray."""
    u, v = np.meshgrid(np.linspace(0, truth.width - 1, n), np.linspace(0, truth.height - 1, n))
    xn = truth.undistort_pixels(np.stack([u.ravel(), v.ravel()], axis=1))
    d = estimated.distort(xn) - truth.distort(xn)
    return float(np.max(np.linalg.norm(d * [truth.K[0, 0], truth.K[1, 1]], axis=1)))


def relative_pose_errors(est: list[Camera], truth: list[Camera], reference: int = 0) -> list[dict]:
    """Errors of each camera's pose relative to camera ``reference`` (independent of the world frame)."""
    out = []
    Te0 = _rt_to_T(est[reference].R, est[reference].t)
    Tt0 = _rt_to_T(truth[reference].R, truth[reference].t)
    for e, t in zip(est, truth):
        Te = _rt_to_T(e.R, e.t) @ np.linalg.inv(Te0)
        Tt = _rt_to_T(t.R, t.t) @ np.linalg.inv(Tt0)
        dR = Te[:3, :3] @ Tt[:3, :3].T
        ang = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
        ce = -Te[:3, :3].T @ Te[:3, 3]
        ct = -Tt[:3, :3].T @ Tt[:3, 3]
        out.append({"camera": e.name, "rotation_deg": float(ang), "centre_m": float(np.linalg.norm(ce - ct))})
    return out
