"""Dataset images: 8-bit RGBA and instance-id PNGs, float32 planar-depth EXRs (atomic writes).

imageio, Pillow and OpenEXR are imported where they are used, so importing the dataset package stays
numpy-only (the Blender add-on bundles this package and has neither).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import atomic_path, atomic_write_bytes
from .model import DatasetError

__all__ = ["encode_png", "write_rgb", "write_ids", "write_depth", "read_image", "read_rgb", "rgb_from_image", "read_ids", "read_depth"]

#: Alpha of every stored RGB pixel: the anchor (room) covers the whole image, so nothing is
#: transparent; D-NeRF and nerfstudio read the 4th channel as alpha (an RGB file would make them
#: read blue as alpha), and with alpha 255 their white-background compositing is the identity.
OPAQUE = 255


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of a ``(H, W)``, ``(H, W, 3)`` or ``(H, W, 4)`` uint8 image.

    Pillow directly (imageio's own PNG writer, byte for byte): imageio's plugin lookup cost a
    third of each small image's time, and Pillow's encoder lets other threads run.
    """
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format="PNG")
    return buf.getvalue()


def write_rgb(path: str | Path, rgb: np.ndarray) -> None:
    """Write an ``(H, W, 3)`` uint8 RGB image atomically, stored as an 8-bit RGBA PNG with alpha 255."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"{path}: RGB must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    alpha = np.full(rgb.shape[:2] + (1,), OPAQUE, np.uint8)
    atomic_write_bytes(path, encode_png(np.concatenate([rgb, alpha], axis=2)))


def write_ids(path: str | Path, ids: np.ndarray) -> None:
    """Write an ``(H, W)`` uint8 instance-id PNG atomically (``NO_OBJECT`` = nothing hit)."""
    ids = np.asarray(ids)
    if ids.dtype != np.uint8 or ids.ndim != 2:
        raise ValueError(f"{path}: instance ids must be (H, W) uint8, got {ids.shape} {ids.dtype}")
    atomic_write_bytes(path, encode_png(ids))


def write_depth(path: str | Path, depth: np.ndarray) -> None:
    """Write ``(H, W)`` planar depth as a float32 single-channel ("Z") EXR, atomically.

    The array is converted to a C-contiguous float32 copy first: OpenEXR writes strided or
    transposed arrays wrong without raising.
    """
    import OpenEXR

    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"{path}: depth must be (H, W), got {depth.shape}")
    data = np.ascontiguousarray(depth, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path, suffix=".exr") as tmp:
        OpenEXR.File(header, {"Z": data}).write(str(tmp))


def _check_exists(path: Path) -> None:
    if not path.exists():
        raise DatasetError(f"{path}: missing file")


def read_image(path: str | Path) -> np.ndarray:
    """An 8-bit image file (PNG, JPEG) as stored: ``(H, W)`` or ``(H, W, C)``, any dtype imageio gives."""
    import imageio.v3 as iio

    path = Path(path)
    _check_exists(path)
    try:
        return iio.imread(path)
    except Exception as e:  # imageio raises many types for corrupt files
        raise DatasetError(f"{path}: cannot read the image ({e})") from None


def read_rgb(path: str | Path) -> np.ndarray:
    """Read an 8-bit RGB(A) image (PNG, or JPEG for ``osn preprocess``) as ``(H, W, 3)`` uint8
    (alpha dropped, grey expanded)."""
    return rgb_from_image(read_image(path), path)


def rgb_from_image(img: np.ndarray, path: str | Path) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB of an image as stored (see :func:`read_rgb`); ``path`` names it in errors."""
    if img.dtype != np.uint8:
        raise DatasetError(f"{path}: expected 8-bit RGB, got {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise DatasetError(f"{path}: expected an RGB image, got shape {img.shape}")
    return np.ascontiguousarray(img[..., :3])


def read_ids(path: str | Path) -> np.ndarray:
    """Read an instance-id PNG as ``(H, W)`` uint8."""
    img = read_image(path)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise DatasetError(f"{path}: instance ids must be a single-channel 8-bit PNG, got {img.shape} {img.dtype}")
    return img


def read_depth(path: str | Path) -> np.ndarray:
    """Read a planar-depth EXR (channel "Z", or the only channel) as ``(H, W)`` float32."""
    import OpenEXR

    path = Path(path)
    _check_exists(path)
    try:
        with OpenEXR.File(str(path)) as f:
            channels = f.channels()
            if "Z" in channels:
                px = channels["Z"].pixels
            elif len(channels) == 1:
                px = next(iter(channels.values())).pixels
            else:
                raise DatasetError(f"{path}: no 'Z' channel (found {sorted(channels)})")
            px = np.array(px)
    except DatasetError:
        raise
    except Exception as e:
        raise DatasetError(f"{path}: cannot read EXR ({e})") from None
    if px.ndim != 2:
        raise DatasetError(f"{path}: depth must be a single channel, got shape {px.shape}")
    return px.astype(np.float32, copy=False)
