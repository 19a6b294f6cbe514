"""The frames SIFT sees, per object: grey (luminance or the object's principal colour axis),
cropped to the object's box, upsampled, and written with the object's eroded mask in COLMAP's
layout. Pure numpy and image files; :mod:`osn.preprocess.sfm` runs COLMAP on them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

GREY_MODES = ("auto", "luminance", "principal")


def upscale(image: np.ndarray, factor: int, order: int = 3) -> np.ndarray:
    """``(H, W[, C]) uint8`` upsampled by an integer factor: cubic spline for images, nearest
    (``order=0``) for masks; pixel centres map as in ``skimage.transform.resize``.

    SIFT finds few features on objects of ~30 pixels; a blocky (nearest) image gives fewer still.
    The result equals ``resize(image, ..., order=order, preserve_range=True, anti_aliasing=False)``
    rounded to uint8 bit for bit (tested), and is faster: that resize runs its spline along the
    colour axis too, which on large frames costs a large part of a small object's SfM.
    """
    if factor == 1:
        return image
    if order == 0:  # each input pixel becomes a factor x factor block: nearest under that mapping
        return image.repeat(factor, 0).repeat(factor, 1)
    from scipy.ndimage import zoom

    chans = image[..., None] if image.ndim == 2 else image
    # skimage's "reflect" is ndimage's "mirror"; it clips to the input's range before we round.
    out = np.stack([zoom(chans[..., c].astype(np.float64), factor, order=order, mode="mirror", grid_mode=True)
                    for c in range(chans.shape[-1])], -1)
    out = np.clip(out, float(image.min()), float(image.max()))
    out = np.clip(np.rint(out), 0, 255).astype(np.uint8)
    return out[..., 0] if image.ndim == 2 else out


def erode(mask: np.ndarray, r: int) -> np.ndarray:
    """``mask`` shrunk by ``r`` pixels (so features do not straddle objects)."""
    if r <= 0:
        return mask
    from scipy.ndimage import binary_erosion

    return binary_erosion(mask, iterations=r)


#: Rec. 709 luma weights, the grey conversion COLMAP applies to colour images.
LUMA = np.array([0.2126, 0.7152, 0.0722])
#: ``grey: auto`` projects on the principal colour axis when the luminance's contrast is below
#: this fraction of that axis' contrast (both on unit colour vectors).
AUTO_GREY_RATIO = 0.5


def principal_grey(images: np.ndarray, masks: np.ndarray, mode: str = "principal") -> np.ndarray | None:
    """``(T,H,W)`` uint8 grey frames for SIFT: RGB projected on the object's principal colour axis.

    SIFT sees grey levels only. An object painted in two colours of about equal luminance (the
    gnome's red and blue) is nearly blank in luminance, but not along the axis joining its
    colours. The axis and the min-max stretch come from the pixels in ``masks`` over all frames,
    so one mapping serves every frame and descriptors stay comparable. With ``mode="auto"`` this
    happens only when luminance has less than ``AUTO_GREY_RATIO`` of the axis' contrast (a
    checker of a light and a dark colour keeps the luminance, whose fine detail a stretch along
    the checker's axis would drown); ``None`` means "use luminance".
    """
    px = images[masks].reshape(-1, 3).astype(np.float64)
    if len(px) < 2:
        return None
    mean = px.mean(axis=0)
    _, _, vt = np.linalg.svd(px - mean, full_matrices=False)
    axis = vt[0] if vt[0] @ LUMA >= 0 else -vt[0]  # brighter colours stay brighter
    if mode == "auto":
        luma_std = np.std(px @ (LUMA / np.linalg.norm(LUMA)))
        if luma_std >= AUTO_GREY_RATIO * np.std(px @ axis):
            return None
    proj = (images.astype(np.float64) - mean) @ axis
    lo, hi = proj[masks].min(), proj[masks].max()
    return np.clip(np.rint((proj - lo) / max(hi - lo, 1e-9) * 255.0), 0, 255).astype(np.uint8)


def crop_box(masks: np.ndarray, margin: int, principal_point: tuple[float, float]) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)``: the box of every True pixel of ``masks (T, H, W)`` grown by ``margin``
    pixels, widened to hold the ``principal_point (cx, cy)`` and clipped to the frame; the whole
    frame when ``margin < 0`` or nothing is set.

    COLMAP's mapper triangulates nothing from cameras whose principal point lies outside their
    image (gnome-house's gnome at 512 px: every initial pair was discarded)."""
    T, H, W = masks.shape
    ys, xs = np.nonzero(masks.any(0))
    if margin < 0 or len(xs) == 0:
        return 0, 0, W, H
    cx, cy = principal_point
    x0, y0 = min(int(xs.min()) - margin, int(np.floor(cx)) - 1), min(int(ys.min()) - margin, int(np.floor(cy)) - 1)
    x1, y1 = max(int(xs.max()) + 1 + margin, int(np.ceil(cx)) + 1), max(int(ys.max()) + 1 + margin, int(np.ceil(cy)) + 1)
    return max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)


def write_colmap_images(
    img_dir: Path, mask_dir: Path, images: np.ndarray, masks: np.ndarray, frames: list[int], object_id: int,
    grey: str, erosion: int, factor: int,
) -> list[str]:
    """Write the ``frames`` SIFT sees (grey per ``grey``, upsampled by ``factor``) and the
    object's masks eroded by ``erosion`` pixels in COLMAP's layout (``NAME.png`` and
    ``NAME.png.png``); returns the image names."""
    import imageio.v3 as iio

    names = []
    frames_img = dict(zip(frames, images[frames]))
    if grey != "luminance":
        projected = principal_grey(images[frames], masks[frames] == object_id, grey)
        if projected is not None:
            frames_img = dict(zip(frames, projected))
    for t in frames:
        n = f"{t:05d}.png"
        names.append(n)
        m = erode(masks[t] == object_id, erosion)
        iio.imwrite(img_dir / n, upscale(frames_img[t], factor))
        iio.imwrite(mask_dir / f"{n}.png", upscale((m * 255).astype(np.uint8), factor, order=0))
    return names
