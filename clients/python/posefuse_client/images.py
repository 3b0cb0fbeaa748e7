"""Images for requests: encoded bytes pass through; numpy arrays are encoded to PNG (lossless,
standard library only) or, when Pillow is installed, to JPEG."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an 8-bit image: [H, W] (grey), [H, W, 3] (RGB) or [H, W, 4] (RGBA)."""
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ValueError(f"image must be uint8, got {a.dtype}")
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4) or a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"image must be [H, W], [H, W, 3] or [H, W, 4], got shape {a.shape}")
    h, w, c = a.shape
    color_type = {1: 0, 3: 2, 4: 6}[c]
    # Filter type 0 (None) before every row.
    raw = np.concatenate([np.zeros((h, 1), np.uint8), np.ascontiguousarray(a).reshape(h, w * c)], axis=1)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", w, h, 8, color_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6)) + chunk(
        b"IEND", b""
    )


def encode_jpeg(image: np.ndarray, quality: int = 90) -> bytes:
    """JPEG bytes of an 8-bit RGB or grey image (needs Pillow: `pip install pillow`)."""
    try:
        from PIL import Image
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("encode_jpeg needs Pillow; use encode_png or pass encoded bytes") from e
    out = io.BytesIO()
    Image.fromarray(np.asarray(image, dtype=np.uint8)).save(out, format="JPEG", quality=quality)
    return out.getvalue()


def image_bytes(image: bytes | np.ndarray | None) -> bytes | None:
    """Encoded image bytes: bytes unchanged (JPEG or PNG file bytes), arrays as PNG."""
    if image is None or isinstance(image, (bytes, bytearray, memoryview)):
        return None if image is None else bytes(image)
    return encode_png(image)
