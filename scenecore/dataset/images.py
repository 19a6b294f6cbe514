"""Dataset images: 8-bit RGBA and instance-id PNGs, float32 planar-depth EXRs (atomic writes).

imageio, Pillow and OpenEXR are imported where they are used, so importing the dataset package stays
numpy-only (the Blender add-on bundles this package and has neither).
"""

from __future__ import annotations

import os
import stat
import struct
from pathlib import Path
from typing import BinaryIO, Iterator, NamedTuple

import numpy as np

from ..atomic import atomic_path, atomic_write_bytes
from .model import DatasetError

__all__ = [
    "encode_png", "write_rgb", "write_ids", "write_depth", "read_image", "read_rgb", "rgb_from_image", "read_ids",
    "read_depth", "MAX_IMAGE_PIXELS", "pixels_problem", "read_regular", "open_regular", "exr_size",
]

#: Alpha of every stored RGB pixel: the anchor (room) covers the whole image, so nothing is
#: transparent; D-NeRF and nerfstudio read the 4th channel as alpha (an RGB file would make them
#: read blue as alpha), and with alpha 255 their white-background compositing is the identity.
OPAQUE = 255

#: Most pixels an image file may declare when no size is expected (8192 x 8192): a header that
#: claims more is refused before anything is decoded, so that a small file (a compressed block of
#: zeros) cannot make a reader allocate gigabytes.
MAX_IMAGE_PIXELS = 1 << 26
#: Most bytes of an EXR header (attributes, a preview image) read before its data window is known.
MAX_EXR_HEADER_BYTES = 1 << 24
#: Most channels of a depth EXR: decoding allocates every channel at full size.
MAX_EXR_CHANNELS = 64


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


def pixels_problem(width: int, height: int) -> str | None:
    """Why an image header declaring ``width x height`` is refused before decoding (None when not):
    empty, or more than :data:`MAX_IMAGE_PIXELS`."""
    if width <= 0 or height <= 0:
        return f"declares an empty image ({width}x{height})"
    if width * height > MAX_IMAGE_PIXELS:
        return f"declares {width}x{height} pixels, more than the {MAX_IMAGE_PIXELS} an image may have"
    return None


def _unreadable(path: str | Path, e: OSError) -> DatasetError:
    if isinstance(e, FileNotFoundError):
        return DatasetError(f"{path}: missing file")
    return DatasetError(f"{path}: cannot read ({e.strerror or e})")


def _regular_stat(path: str | Path, fd: int | None = None) -> os.stat_result:
    """``path``'s status (of the open ``fd`` when given), or ``DatasetError`` naming it when it is
    missing or not a regular file: a FIFO blocks its reader and a device (a link to ``/dev/zero``)
    never ends."""
    try:
        st = os.fstat(fd) if fd is not None else os.stat(path)
    except OSError as e:
        raise _unreadable(path, e) from None
    if not stat.S_ISREG(st.st_mode):
        what = ("a directory" if stat.S_ISDIR(st.st_mode) else "a FIFO" if stat.S_ISFIFO(st.st_mode)
                else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else "a special file")
        raise DatasetError(f"{path}: not a regular file ({what})")
    return st


def _open_regular(path: str | Path) -> tuple[BinaryIO, int]:
    """``path`` opened for reading and its size; opening does not block on a FIFO, and the opened
    file itself must be regular (see :func:`_regular_stat`)."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    except OSError as e:
        raise _unreadable(path, e) from None
    try:
        size = _regular_stat(path, fd).st_size
    except BaseException:
        os.close(fd)
        raise
    return os.fdopen(fd, "rb"), size


def open_regular(path: str | Path) -> tuple[BinaryIO, int]:
    """``path`` opened for reading and its size when opened, for readers that stream it
    (``benchgen.score.digests`` hashes in chunks); ``DatasetError`` naming it when it is
    missing or not a regular file, without blocking on a FIFO."""
    return _open_regular(path)


def read_pieces(fh: BinaryIO, size: int, path: str | Path, piece: int) -> Iterator[bytes]:
    """The bytes of the open regular file ``fh`` in pieces of at most ``piece``, exactly the
    ``size`` it had when opened; ``DatasetError`` naming ``path`` when it grew or shrank. Each call
    asks for one byte more than is left, so a file that grew shows it without a further call, and
    a regular file's read comes back short only at its end (readers of many small files pay per call)."""
    fd, left = fh.fileno(), size
    while True:
        want = min(piece, left + 1)
        chunk = os.read(fd, want)
        if len(chunk) > left:
            raise DatasetError(f"{path}: changed size while being read")
        left -= len(chunk)
        if chunk:
            yield chunk
        if len(chunk) < want:
            break
    if left:
        raise DatasetError(f"{path}: changed size while being read")


def read_regular(path: str | Path, max_bytes: int) -> bytes:
    """The bytes of ``path``, a regular file of at most ``max_bytes`` (what such a file can
    legitimately hold), else ``DatasetError`` naming it; only the size it had when opened is read
    (:func:`read_pieces`, in one call)."""
    fh, size = _open_regular(path)
    with fh:
        if size > max_bytes:
            raise DatasetError(f"{path}: {size} bytes, more than the {max_bytes} such a file can hold")
        return b"".join(read_pieces(fh, size, path, size + 1))


def read_image(path: str | Path) -> np.ndarray:
    """An 8-bit image file (PNG, JPEG) as stored: ``(H, W)`` or ``(H, W, C)``, any dtype imageio gives."""
    import imageio.v3 as iio

    path = Path(path)
    _regular_stat(path)
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


#: EXR pixel types (UINT, HALF, FLOAT) and their bytes per sample.
_EXR_SAMPLE_BYTES = {0: 4, 1: 2, 2: 4}
_EXR_MAGIC = b"\x76\x2f\x31\x01"
#: Version-field flags of EXR files with deep data or several parts, which depth maps never are.
_EXR_DEEP_OR_MULTIPART = 0x800 | 0x1000


class _ExrHeader(NamedTuple):
    height: int
    width: int
    pixel_bytes: int  # bytes of one pixel's samples over every channel
    header_bytes: int
    file_bytes: int


def _exr_pixel_bytes(chlist: bytes, path: Path) -> int:
    """Bytes per pixel over the channels of a ``chlist`` attribute (each: name, NUL, int32 pixel
    type, pLinear, 3 reserved bytes, int32 x and y sampling; a NUL ends the list)."""
    total, count, pos = 0, 0, 0
    while chlist[pos] != 0:
        end = chlist.index(b"\0", pos)
        total += _EXR_SAMPLE_BYTES.get(struct.unpack_from("<i", chlist, end + 1)[0], 4)
        count, pos = count + 1, end + 17
        if count > MAX_EXR_CHANNELS:
            raise DatasetError(f"{path}: more than {MAX_EXR_CHANNELS} channels; a depth EXR needs one")
    return total


def _exr_attributes(head: bytes) -> tuple[dict[bytes, tuple[bytes, bytes]], int] | None:
    """The attributes ``{name: (type, value)}`` after an EXR's magic and version (each ``name NUL
    type NUL int32-size value``, an empty name ends them) and the header's length; None when
    ``head`` ends inside the header."""
    attrs: dict[bytes, tuple[bytes, bytes]] = {}
    pos = 8
    while pos < len(head):
        if head[pos] == 0:
            return attrs, pos + 1
        end_name = head.find(b"\0", pos)
        end_type = head.find(b"\0", end_name + 1) if end_name >= 0 else -1
        if end_type < 0 or end_type + 5 > len(head):
            return None
        (n,) = struct.unpack_from("<i", head, end_type + 1)
        if n < 0:
            raise ValueError("negative attribute size")
        attrs[head[pos:end_name]] = (head[end_name + 1 : end_type], head[end_type + 5 : end_type + 5 + n])
        pos = end_type + 5 + n
    return None


def _exr_header(path: Path) -> _ExrHeader:
    """The sizes of a single-part EXR from its header alone (read in growing pieces up to
    :data:`MAX_EXR_HEADER_BYTES`, nothing decoded); ``DatasetError`` naming the file when it is
    not such an EXR."""
    fh, file_bytes = _open_regular(path)
    with fh:
        head = fh.read(min(file_bytes, 1 << 16))
        if head[:4] != _EXR_MAGIC or len(head) < 8:
            raise DatasetError(f"{path}: cannot read EXR (not an EXR file)")
        if struct.unpack_from("<i", head, 4)[0] & _EXR_DEEP_OR_MULTIPART:
            raise DatasetError(f"{path}: cannot read EXR (deep or multi-part; depth must be a single-part image)")
        try:
            while (parsed := _exr_attributes(head)) is None:
                more = fh.read(min(len(head), MAX_EXR_HEADER_BYTES - len(head)))
                if not more:
                    raise ValueError("truncated")
                head += more
            attrs, header_bytes = parsed
            if attrs[b"dataWindow"][0] != b"box2i" or attrs[b"channels"][0] != b"chlist":
                raise ValueError("dataWindow or channels of the wrong type")
            x0, y0, x1, y1 = struct.unpack_from("<4i", attrs[b"dataWindow"][1])
            pixel_bytes = _exr_pixel_bytes(attrs[b"channels"][1], path)
        except DatasetError:
            raise
        except (ValueError, IndexError, KeyError, struct.error):
            raise DatasetError(f"{path}: cannot read EXR (corrupt or truncated header, or one over "
                               f"{MAX_EXR_HEADER_BYTES} bytes)") from None
    return _ExrHeader(y1 - y0 + 1, x1 - x0 + 1, pixel_bytes, header_bytes, file_bytes)


def exr_size(path: str | Path) -> tuple[int, int]:
    """``(H, W)`` of an EXR's data window, read from its header only (nothing is decoded), so that
    a caller expecting a size can refuse another before decoding."""
    h = _exr_header(Path(path))
    return h.height, h.width


def read_depth(path: str | Path) -> np.ndarray:
    """Read a planar-depth EXR (channel "Z", or the only channel) as ``(H, W)`` float32.

    The header is checked before decoding (a few hundred kilobytes of compressed zeros can
    declare gigabytes of pixels): a regular file, at most :data:`MAX_IMAGE_PIXELS` pixels and
    :data:`MAX_EXR_CHANNELS` channels, and no larger than its pixels stored uncompressed allow.
    Callers expecting a size check it first with :func:`exr_size`.
    """
    import OpenEXR

    path = Path(path)
    h = _exr_header(path)
    if p := pixels_problem(h.width, h.height):
        raise DatasetError(f"{path}: {p}")
    # Its samples uncompressed with line or tile headers, offsets and mipmap levels, twice over.
    bound = h.header_bytes + 4 * h.height * h.width * (h.pixel_bytes + 8) + (1 << 20)
    if h.file_bytes > bound:
        raise DatasetError(f"{path}: {h.file_bytes} bytes, more than the {bound} an EXR of "
                           f"{h.width}x{h.height} can hold")
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
