"""Reading a recording's colour and depth image files, with one-line errors naming the frame and the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from ..core.camera import Camera
from .errors import DatasetError


def _read_image(path: Path, index: int, what: str, camera: Camera | None = None) -> o3d.t.geometry.Image:
    from .image_header import check_declared_size

    from ..io.inputs import check_regular, printable

    if not path.is_file() and not path.is_symlink() and not path.exists():
        raise DatasetError(f"frame {index}: {what} file {printable(path)} does not exist")
    check_regular(path, f"{what} file of frame {index}", DatasetError)  # a FIFO, a device, a looping link
    # the header first: a small file may declare a huge image, refused before it is decoded
    check_declared_size(path, index, what, None if camera is None else (camera.width, camera.height))
    if path.suffix.lower() in (".jpg", ".jpeg") and not _jpeg_complete(path):
        # libjpeg decodes a cut-off JPEG without an error (the missing rows grey): a truncated file, not a frame
        raise DatasetError(f"frame {index}: {what} file {path} is truncated (no JPEG end-of-image marker)")
    try:
        image = o3d.t.io.read_image(str(path))
    except Exception as e:  # Open3D raises only for odd cases; most failures give an empty image
        raise DatasetError(f"frame {index}: cannot read {what} file {path}: {e}") from None
    if image.is_empty():
        raise DatasetError(f"frame {index}: {what} file {path} is corrupt or not an image")
    return image


def _jpeg_complete(path: Path, tail: int = 64) -> bool:
    """Whether a JPEG file ends with its end-of-image marker (FF D9), allowing a little padding after it."""
    with open(path, "rb") as f:
        f.seek(0, 2)
        f.seek(max(0, f.tell() - tail))
        return b"\xff\xd9" in f.read()


def _check_size(image: o3d.t.geometry.Image, path: Path, index: int, what: str, camera: Camera) -> None:
    if (image.rows, image.columns) != (camera.height, camera.width):
        raise DatasetError(f"frame {index}: {what} file {path} is {image.columns}x{image.rows} but the intrinsics "
                           f"are for {camera.width}x{camera.height}")


def read_color(path: Path, index: int, camera: Camera) -> o3d.t.geometry.Image:
    """Colour image as UInt8 [H, W, 3] RGB (grey is repeated, alpha dropped, 16-bit scaled to 8-bit)."""
    image = _read_image(path, index, "colour", camera)
    _check_size(image, path, index, "colour", camera)
    if image.dtype == o3d.core.uint8 and image.channels == 3:
        return image
    a = image.as_tensor().numpy()
    if a.dtype == np.uint16:
        a = (a // 257).astype(np.uint8)
    elif a.dtype != np.uint8:
        raise DatasetError(f"frame {index}: colour file {path} has unsupported type {image.dtype}")
    a = a.reshape(a.shape[0], a.shape[1], -1)
    a = np.repeat(a[..., :1], 3, axis=2) if a.shape[2] in (1, 2) else a[..., :3]
    return o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(a)))


def read_depth(path: Path, index: int, camera: Camera) -> o3d.t.geometry.Image:
    """Depth image as UInt16 [H, W, 1] raw units (a 16-bit single-channel PNG)."""
    image = _read_image(path, index, "depth", camera)
    _check_size(image, path, index, "depth", camera)
    if image.channels != 1 or image.dtype not in (o3d.core.uint16, o3d.core.float32):
        raise DatasetError(f"frame {index}: depth file {path} must be a single-channel 16-bit image, got "
                           f"{image.channels} channel(s) of {image.dtype}")
    return image
