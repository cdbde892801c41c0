"""Image files: OpenEXR (data) and sRGB PNG (for people).

Conventions (docs/conventions.md): arrays are ``(H, W, C)``, linear sRGB, C = 3 (R, G, B)
or 4 (R, G, B, A with premultiplied colour). EXRs are written half float by default,
always atomically (temporary name in the same folder, fsync, rename), so a crash
never leaves a half-written file under the final name.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .formats.files import atomic_target, atomic_write_bytes
from .errors import MifacerfError

#: Rec. 709 luminance of linear RGB (the weights of R, G, B)
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])

EXR_MAGIC = b"\x76\x2f\x31\x01"


class ImageFileError(MifacerfError, OSError):
    """A missing, truncated, corrupt or inconsistent image file; the message names it."""


def write_exr(path: str | os.PathLike, image: np.ndarray, half: bool = True,
              check_finite: bool = True) -> None:
    """Write ``image`` (H, W, 3|4) to an OpenEXR file atomically.

    Channels R, G, B (, A); half float unless ``half=False``; ZIP compression.
    Raises ValueError for a wrong shape or non-finite pixels (when ``check_finite``)
    and for values that overflow half float (|x| > 65504).
    """
    import OpenEXR

    path = Path(path)
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ValueError(f"{path}: expected an (H, W, 3|4) image, got shape {image.shape}")
    if check_finite and not np.isfinite(image).all():
        bad = int((~np.isfinite(image)).any(axis=2).sum())
        raise ValueError(f"{path}: refusing to write {bad} pixel(s) with NaN/Inf values")
    if half and np.abs(image).max(initial=0.0) > 65504.0:
        raise ValueError(f"{path}: values up to {np.abs(image).max():.4g} overflow half float (65504); "
                         "scale the data or write full float")
    dtype = np.float16 if half else np.float32
    data = np.ascontiguousarray(image.astype(dtype))
    channels = {"RGB": np.ascontiguousarray(data[..., :3])}
    if image.shape[2] == 4:
        channels["A"] = np.ascontiguousarray(data[..., 3])
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    tmp = atomic_target(path)
    try:
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp))
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if tmp.exists():
            tmp.unlink()
        raise


def read_exr(path: str | os.PathLike, channels: int | None = None,
             expect_shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read an OpenEXR file into a float32 array (H, W, C).

    ``channels`` = 3 returns RGB only, 4 requires alpha. ``expect_shape`` = (H, W)
    checks the resolution. Every failure raises :class:`ImageFileError` naming the
    file and the problem (missing, not an EXR, truncated/corrupt, wrong size,
    missing channels, NaN/Inf pixels).
    """
    import OpenEXR

    path = Path(path)
    if not path.exists():
        raise ImageFileError(f"{path}: missing image file")
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic != EXR_MAGIC:
        raise ImageFileError(f"{path}: not an OpenEXR file (bad magic number)")
    try:
        with OpenEXR.File(str(path)) as f:
            chans = {k: v.pixels for k, v in f.channels().items()}
    except Exception as exc:  # OpenEXR raises RuntimeError for truncated/corrupt data
        raise ImageFileError(f"{path}: truncated or corrupt OpenEXR file ({exc})") from exc
    if "RGBA" in chans:  # the bindings merge R, G, B, A into one array
        rgba = chans.pop("RGBA")
        chans["RGB"], chans["A"] = rgba[..., :3], rgba[..., 3]
    if "RGB" in chans:
        rgb = chans["RGB"]
    elif all(c in chans for c in "RGB"):
        rgb = np.stack([chans["R"], chans["G"], chans["B"]], axis=-1)
    elif "Y" in chans:
        rgb = np.repeat(chans["Y"][..., None], 3, axis=-1)
    else:
        raise ImageFileError(f"{path}: no R, G, B channels (has {sorted(chans)})")
    planes = [np.asarray(rgb, np.float32)]
    if channels == 4 or (channels is None and "A" in chans):
        if "A" not in chans:
            raise ImageFileError(f"{path}: no alpha channel")
        planes.append(np.asarray(chans["A"], np.float32)[..., None])
    image = np.concatenate(planes, axis=-1) if len(planes) > 1 else planes[0]
    if expect_shape is not None and tuple(image.shape[:2]) != tuple(expect_shape):
        raise ImageFileError(f"{path}: image is {image.shape[1]}x{image.shape[0]}, "
                             f"expected {expect_shape[1]}x{expect_shape[0]}")
    if not np.isfinite(image).all():
        raise ImageFileError(f"{path}: contains NaN/Inf pixels")
    return image


def to_srgb8(image: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear sRGB (H, W, 3|4) → 8-bit sRGB-encoded (H, W, 3|4); alpha stays linear."""
    img = np.nan_to_num(np.asarray(image, np.float64)) * 1.0
    rgb = np.clip(img[..., :3] * exposure, 0.0, 1.0)
    enc = np.where(rgb <= 0.0031308, 12.92 * rgb, 1.055 * np.power(rgb, 1 / 2.4) - 0.055)
    out = [enc]
    if img.shape[-1] == 4:
        out.append(np.clip(img[..., 3:4], 0.0, 1.0))
    return (np.concatenate(out, axis=-1) * 255.0 + 0.5).astype(np.uint8)


def write_png(path: str | os.PathLike, image: np.ndarray, exposure: float = 1.0) -> None:
    """Write linear data as an sRGB PNG (8-bit), atomically; uint8 input is written as is."""
    import cv2

    image = np.asarray(image)
    img8 = image if image.dtype == np.uint8 else to_srgb8(image, exposure)
    if img8.ndim == 2:
        bgr = img8
    elif img8.shape[-1] == 4:
        bgr = cv2.cvtColor(img8, cv2.COLOR_RGBA2BGRA)
    else:
        bgr = cv2.cvtColor(img8, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise ImageFileError(f"{path}: PNG encoding failed")
    atomic_write_bytes(path, buf.tobytes())


def read_hdr_or_exr(path: str | os.PathLike) -> np.ndarray:
    """Read a linear RGB image from .exr (OpenEXR) or .hdr (Radiance RGBE) as float32 (H, W, 3)."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        return read_exr(path, channels=3)
    import cv2

    if not path.exists():
        raise ImageFileError(f"{path}: missing image file")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
    if img is None or img.ndim != 3:
        raise ImageFileError(f"{path}: cannot read as an HDR image")
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32)
    if not np.isfinite(img).all():
        raise ImageFileError(f"{path}: contains NaN/Inf pixels")
    return img
