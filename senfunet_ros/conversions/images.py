"""Images: sensor_msgs/Image (and CompressedImage) -> numpy depth and colour, resizing, intrinsics.

Convention: depth is float32 (H, W) metres with invalid pixels set to 0; RGB is uint8 (H, W, 3).
Every failure is a ValueError saying what was wrong and what to do about it.
"""
from __future__ import annotations

import math
import re
import warnings
from typing import Any

import numpy as np

from senfunet_ros.conversions.rvl import rvl_decode

__all__ = [
    "depth_from_image",
    "depth_units_note",
    "color_for_depth",
    "intrinsics_for_size",
    "principal_point_off_centre",
    "same_aspect_ratio",
    "intrinsics_from_camera_info",
    "rectified_matrix",
    "intrinsics_text",
    "resize_depth",
    "resize_rgb",
    "rgb_from_image",
    "scale_intrinsics",
]

# Pillow modes of 16-bit and float images: not colour (an IR or depth image on the colour topic)
_WIDE_MODES = ("I", "I;16", "I;16B", "I;16L", "I;16N", "F")
_DEPTH_ENCODINGS: dict[str, tuple[str, float]] = {
    # encoding -> (numpy dtype without byte order, scale to metres)
    "32FC1": ("f4", 1.0),
    "16UC1": ("u2", 1e-3),
    "mono16": ("u2", 1e-3),  # some drivers label millimetre depth as mono16
}

_COLOR_ENCODINGS: dict[str, int] = {"rgb8": 3, "bgr8": 3, "mono8": 1, "rgba8": 4, "bgra8": 4}


def _image_rows(msg: Any, bytes_per_pixel: int) -> np.ndarray:
    """The image payload as (H, W * bytes_per_pixel) uint8, honouring `step` row padding."""
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height <= 0 or width <= 0:
        raise ValueError(f"image is empty ({width}x{height}); the driver published no pixels")
    row_bytes = width * bytes_per_pixel
    if step < row_bytes:
        raise ValueError(
            f"image step {step} B is shorter than width {width} x {bytes_per_pixel} B per pixel; "
            "fix the driver's step field"
        )
    data = (np.frombuffer(msg.data, dtype=np.uint8) if not isinstance(msg.data, np.ndarray)
            else msg.data.view(np.uint8).ravel())
    if data.size < step * height:
        raise ValueError(
            f"image data has {data.size} B but step x height = {step * height} B; "
            "the message is truncated or its step/height are wrong"
        )
    return data[: step * height].reshape(height, step)[:, :row_bytes]


def _is_compressed(msg: Any) -> bool:
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


# image_transport's compressed_depth_image_transport: a 12-byte ConfigHeader (int32 format, float32
# depthParam[2]) before the PNG; 16UC1 depth is stored as it is, 32FC1 as quantised inverse depth.
_COMPRESSED_DEPTH_HEADER = np.dtype([("format", "<i4"), ("depth_a", "<f4"), ("depth_b", "<f4")])


# a compressed image's pixels at most (from its header, before decoding): 8K video is 33 Mpx
MAX_COMPRESSED_PIXELS = 64_000_000


class _TooLarge(ValueError):
    """A compressed image whose header gives more than MAX_COMPRESSED_PIXELS."""


def _decode(data: np.ndarray, what: str, *, color: bool) -> np.ndarray:
    """A png/jpeg payload -> (H, W) as stored (color=False) or (H, W, 3) RGB uint8 (color=True).

    Pillow, not OpenCV: OpenCV's libpng and libjpeg print a line of their own to stderr for every
    corrupt image ("libpng error: ...", "Corrupt JPEG data: ..."), unthrottled, once per message; the
    caller's error says the same, counted and rate-limited (the node's log, ~/status)."""
    import io

    from PIL import Image as PilImage

    if not data.size:
        raise ValueError(f"{what} is empty; check the publisher's image_transport")
    try:
        with warnings.catch_warnings():  # Pillow's decompression-bomb warning: the size is checked below
            warnings.simplefilter("ignore", PilImage.DecompressionBombWarning)
            image = PilImage.open(io.BytesIO(data.tobytes()))
        with image:
            width, height = image.size  # from the header: an image too large for any camera is not decoded
            if width * height > MAX_COMPRESSED_PIXELS:
                raise _TooLarge(f"{what} is {width}x{height} pixels, more than any camera's "
                                f"({MAX_COMPRESSED_PIXELS / 1e6:.0f} Mpx): not decoded; check its publisher")
            image.load()
            mode = image.mode
            # np.array, not asarray: Pillow's arrays are read-only, and the frame's users may write
            if not color:
                return np.array(image)
            if mode not in _WIDE_MODES:
                return np.array(image.convert("RGB") if mode != "RGB" else image, np.uint8)
    except _TooLarge as err:
        raise ValueError(str(err)) from None
    except Exception as err:  # noqa: BLE001 (Pillow raises OSError, SyntaxError, struct.error... on corrupt data)
        reason = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
        reason = re.sub(r" <_io\.BytesIO object at 0x[0-9a-fA-F]+>", "", reason)  # an address, new in every message
        raise ValueError(f"{what} is not a readable png/jpeg image ({reason}); check the publisher's "
                         "image_transport") from None
    # converted to RGB, 16-bit or float values are clipped to 255: a nearly white image
    raise ValueError(f"{what} is a {mode} (16-bit or float) image, not 8-bit colour: publish the colour camera's 8-bit "
                     "images (rgb8/bgr8/mono8) on the colour topic")


def _compressed_depth_codec(fmt: str) -> str:
    """'png' or 'rvl' from a compressedDepth format such as '16UC1; compressedDepth rvl' (without a
    codec, '16UC1; compressedDepth' or 'compressedDepth', png: as older publishers write it)."""
    if "compressedDepth" not in fmt:
        raise ValueError(f"compressed depth format '{fmt}' is not compressedDepth; publish depth through "
                         "image_transport's compressedDepth (png or rvl)")
    codec = fmt.split("compressedDepth", 1)[1].strip() or "png"
    if codec not in ("png", "rvl"):
        raise ValueError(f"compressedDepth codec '{codec}' (format '{fmt}') is not supported; "
                         "publish compressedDepth png or rvl")
    return codec


def depth_from_compressed(msg: Any) -> np.ndarray:
    """sensor_msgs/CompressedImage as image_transport's compressedDepth writes it -> depth_m float32
    (H, W): format '16UC1; compressedDepth png|rvl' (millimetres) or '32FC1; compressedDepth png|rvl'
    (inverse depth quantised with the header's parameters)."""
    fmt = str(msg.format)
    data = np.frombuffer(bytes(msg.data), np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data.view(np.uint8)
    codec = _compressed_depth_codec(fmt)
    encoding = fmt.split(";")[0].strip()
    if data.size < _COMPRESSED_DEPTH_HEADER.itemsize:
        raise ValueError(f"compressedDepth message has {data.size} B, less than its 12-byte header")
    header = data[:_COMPRESSED_DEPTH_HEADER.itemsize].view(_COMPRESSED_DEPTH_HEADER)[0]
    if encoding.startswith("compressedDepth"):  # a format without the encoding: the header's quantisation tells
        encoding = "32FC1" if header["depth_a"] or header["depth_b"] else "16UC1"
    if encoding not in ("16UC1", "mono16", "32FC1"):
        raise ValueError(f"compressedDepth encoding '{encoding}' is not supported; publish 16UC1 or 32FC1")
    payload = data[_COMPRESSED_DEPTH_HEADER.itemsize:]
    if codec == "rvl":
        raw = rvl_decode(payload)
    else:
        raw = _decode(payload, "compressedDepth payload", color=False)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise ValueError(f"compressedDepth payload is {raw.dtype} with {raw.ndim} dims; "
                             "expected a 16-bit single-channel png")
    if encoding == "32FC1":
        a, b = float(header["depth_a"]), float(header["depth_b"])
        if not (math.isfinite(a) and math.isfinite(b) and a > 0.0):
            raise ValueError(f"compressedDepth 32FC1 header's quantisation (depthParam {a:g}, {b:g}) gives no depth: "
                             "depthParam[0] must be positive and both finite; check the publisher's "
                             "compressed_depth_image_transport")
        with np.errstate(divide="ignore", invalid="ignore"):
            depth_m = (a / (raw.astype(np.float32) - b)).astype(np.float32)
        depth_m[raw == 0] = 0.0
    else:
        depth_m = raw.astype(np.float32) * np.float32(1e-3)
    depth_m[~np.isfinite(depth_m) | (depth_m <= 0.0)] = 0.0
    return depth_m


def rgb_from_compressed(msg: Any) -> np.ndarray:
    """sensor_msgs/CompressedImage (jpeg or png, image_transport's 'compressed') -> rgb uint8 (H, W, 3)."""
    data = np.frombuffer(bytes(msg.data), np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data.view(np.uint8)
    return _decode(data, f"compressed colour image (format '{msg.format}')", color=True)


def depth_from_image(msg: Any) -> np.ndarray:
    """sensor_msgs/Image (32FC1 metres or 16UC1 millimetres), or a compressedDepth CompressedImage,
    -> depth_m float32 (H, W).

    0, NaN, inf and negative values are invalid and come out as 0.
    """
    if _is_compressed(msg):
        return depth_from_compressed(msg)
    encoding = str(msg.encoding)
    if encoding not in _DEPTH_ENCODINGS:
        raise ValueError(
            f"depth encoding '{encoding}' is not supported; publish 32FC1 (metres) or 16UC1 (millimetres)"
        )
    kind, scale = _DEPTH_ENCODINGS[encoding]
    itemsize = int(kind[1])
    rows = _image_rows(msg, itemsize)
    if msg.is_bigendian and itemsize == 2 and _smoother_swapped(rows):  # refused: fused, it would be noise
        raise ValueError(f"{encoding} depth with is_bigendian set reads far smoother as little-endian (neighbouring "
                         "pixels closer): the flag is wrong, and read as it says the image is noise; fix the "
                         "driver's is_bigendian")
    dtype = np.dtype((">" if msg.is_bigendian else "<") + kind)
    raw = np.ascontiguousarray(rows).view(dtype)  # HxW
    depth_m = raw.astype(np.float32) * np.float32(scale)
    depth_m[~np.isfinite(depth_m) | (depth_m <= 0.0)] = 0.0
    return depth_m


def depth_units_note(msg: Any, depth_m: np.ndarray) -> str | None:
    """What a decoded depth image's deepest value says of its encoding, when it looks wrong: float
    depths beyond 1 km or denormal with is_bigendian set (a little-endian driver that sets the flag;
    16-bit depth with the flag wrong is refused by `depth_from_image`), or a millimetre encoding whose
    values stay below 2 cm (metres written as whole numbers). None when nothing looks wrong (or for
    compressedDepth, whose codec fixes the units)."""
    if _is_compressed(msg):
        return None
    encoding = str(msg.encoding)
    millimetres = _DEPTH_ENCODINGS[encoding][1] != 1.0
    if not (msg.is_bigendian or millimetres):  # little-endian metres, the usual: no pass over the image
        return None
    deepest_m = float(depth_m.max(initial=0.0))  # invalid pixels are 0
    # byte-swapped floats are absurdly far, or (a smooth surface: the low mantissa bytes zero) denormals
    if msg.is_bigendian and (deepest_m > 1000.0 or (not millimetres and 0.0 < deepest_m < 1e-6)):
        return (f"its {encoding} depth images have is_bigendian set and decode to depths up to {deepest_m:.3g} m: if "
                "the driver writes little-endian values (as x86 and ARM machines do), the flag is wrong; fix the "
                "driver's is_bigendian")
    if millimetres and 0.0 < deepest_m < 0.02:
        return (f"its {encoding} depth images hold at most {deepest_m * 1000:.0f}, read as millimetres (REP 118): "
                f"metres written as whole numbers into a {encoding} image? Publish millimetres in 16UC1, or metres "
                "in 32FC1")
    return None


def _smoother_swapped(rows: np.ndarray) -> bool:
    """Whether 16-bit pixels (rows of bytes) read little-endian are far smoother than read big-endian: the
    median step between horizontal neighbours (both valid), ten times smaller. Depth is smooth on the
    whole; its byte-swapped values jump by multiples of 256 from pixel to pixel."""
    steps = []
    for order in "<>":
        values = np.ascontiguousarray(rows).view(order + "u2").astype(np.int32)
        both = (values[:, 1:] > 0) & (values[:, :-1] > 0)
        if both.sum() < 100:
            return False
        steps.append(float(np.median(np.abs(np.diff(values, axis=1))[both])))
    return 10.0 * steps[0] < steps[1]


def rgb_from_image(msg: Any) -> np.ndarray:
    """sensor_msgs/Image rgb8/bgr8/mono8 (also rgba8/bgra8), or a jpeg/png CompressedImage, -> rgb uint8 (H, W, 3)."""
    if _is_compressed(msg):
        return rgb_from_compressed(msg)
    encoding = str(msg.encoding)
    if encoding not in _COLOR_ENCODINGS:
        raise ValueError(f"colour encoding '{encoding}' is not supported; publish rgb8, bgr8, rgba8, bgra8 or mono8 "
                         "(a Bayer or YUV camera: debayer or convert it first, e.g. with image_proc)")
    channels = _COLOR_ENCODINGS[encoding]
    rows = _image_rows(msg, channels)
    pixels = rows.reshape(rows.shape[0], -1, channels)  # HxWxC
    if encoding == "mono8":
        return np.repeat(pixels, 3, axis=2)
    if encoding.startswith("bgr"):
        return np.ascontiguousarray(pixels[:, :, 2::-1])
    return np.ascontiguousarray(pixels[:, :, :3])


# The fields of view a depth camera's K may give: beyond, K is a placeholder (a driver's identity K) or
# in other units, and its rays would smear each frame over the map.
MIN_FOV_DEG, MAX_FOV_DEG = 0.5, 170.0


def _row_major(matrix: np.ndarray) -> str:
    """A matrix's rows for a message: 'a b c, d e f'."""
    return ", ".join(" ".join(f"{value:g}" for value in row) for row in matrix)


# image_transport's topics of a transported image: its base topic then one of these
TRANSPORT_SUFFIXES = ("compressed", "compressedDepth", "theora", "zstd", "ffmpeg", "foxglove")


def names_raw_image(topic: str) -> bool:
    """Whether an image topic's name says its images are unrectified, as ROS names them (`image_raw`,
    `depth/image_raw`; not `image_rect_raw` or `image_rect`), after any image_transport suffix."""
    parts = [part for part in topic.split("/") if part]
    while parts and parts[-1] in TRANSPORT_SUFFIXES:
        parts.pop()
    name = parts[-1].lower() if parts else ""
    return "raw" in name and "rect" not in name


def rectified_matrix(msg: Any, *, raw: bool = False) -> np.ndarray | None:
    """The intrinsics (3x3) of P, the projection matrix, when a camera_info describes rectified images
    with them: its distortion coefficients are not all zero and P's left 3x3 is a camera matrix other
    than K (image_proc's and stereo_image_proc's rectified images carry their raw camera's K and D,
    and P for themselves, which image_geometry and depth_image_proc read). Else None: K holds, as it
    does for images their topic names raw (`raw`, `names_raw_image`)."""
    if raw:
        return None
    d = np.asarray(getattr(msg, "d", ()), np.float64)
    p = np.asarray(getattr(msg, "p", ()), np.float64)
    k = np.asarray(getattr(msg, "k", ()), np.float64)
    if not np.any(d != 0) or p.size != 12 or k.size != 9:
        return None
    P = p.reshape(3, 4)[:, :3].copy()
    is_camera_matrix = (np.all(np.isfinite(P)) and P[0, 0] > 0 and P[1, 1] > 0
                        and np.allclose(P[2], (0.0, 0.0, 1.0), rtol=0.0, atol=1e-6))
    if not is_camera_matrix or np.allclose(P, k.reshape(3, 3), rtol=1e-6, atol=1e-9):
        return None
    # a placeholder P (identity, focal lengths in mm) describes no image: K holds
    width, height = int(getattr(msg, "width", 0)), int(getattr(msg, "height", 0))
    fovs_deg = np.degrees(2.0 * np.arctan2(np.array([width, height]) / 2.0, np.array([P[0, 0], P[1, 1]])))
    return P if np.all((MIN_FOV_DEG <= fovs_deg) & (fovs_deg <= MAX_FOV_DEG)) else None


def intrinsics_from_camera_info(msg: Any, *, raw: bool = False) -> tuple[np.ndarray, tuple[int, int]]:
    """sensor_msgs/CameraInfo -> (K 3x3 float64, (width, height)) of the images it describes: K, or P's
    intrinsics for rectified images (`rectified_matrix`; raw: the images are unrectified, K holds).

    K, width and height are the calibrated (full, unbinned) camera's; a region of interest (`roi`,
    in full-resolution pixels; all zero = the whole image) and binning (`binning_x`, `binning_y`;
    0 = 1), as image_proc's crop/decimate sets them, make the published image smaller: the result is
    the K and size of that image (a binned pixel's centre is the centre of the pixels it combines)."""
    k = np.asarray(msg.k, dtype=np.float64)
    if k.size != 9:
        raise ValueError(f"camera_info K has {k.size} entries, expected 9 (row-major 3x3)")
    K = k.reshape(3, 3).copy()
    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise ValueError(f"camera_info size {width}x{height} is empty; set width and height in the driver")
    if not np.all(np.isfinite(K)):
        raise ValueError(f"camera_info K has entries that are not finite numbers ({_row_major(K)}); calibrate "
                         "the camera")
    if K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
        raise ValueError(f"camera_info K has no positive finite focal lengths (fx={K[0, 0]}, fy={K[1, 1]}); "
                         "calibrate the camera")
    if not np.allclose(K[2], (0.0, 0.0, 1.0), rtol=0.0, atol=1e-6):
        # a transposed K (column-major, the principal point in its last row) would shift every ray
        raise ValueError(f"camera_info K is not a camera matrix: its last row is {_row_major(K[2:])}, not 0 0 1 "
                         f"(K = {_row_major(K)}; row-major: fx 0 cx, 0 fy cy, 0 0 1); was it written "
                         "column-major? fix the driver's camera_info")
    rectified = rectified_matrix(msg, raw=raw)
    K = K if rectified is None else rectified
    roi = getattr(msg, "roi", None)
    x0, y0, roi_width, roi_height = (int(getattr(roi, name, 0)) for name in ("x_offset", "y_offset", "width",
                                                                                "height"))
    if roi_width == 0 and roi_height == 0:  # the whole image (from its offset, as image_geometry reads it)
        roi_width, roi_height = width - x0, height - y0
    if roi_width <= 0 or roi_height <= 0 or x0 + roi_width > width or y0 + roi_height > height:
        raise ValueError(f"camera_info roi ({roi_width}x{roi_height} at {x0},{y0}) does not lie within the "
                         f"calibrated {width}x{height} image; fix the driver's roi")
    bin_x, bin_y = (max(1, int(getattr(msg, name, 0))) for name in ("binning_x", "binning_y"))
    if (x0, y0, roi_width, roi_height, bin_x, bin_y) != (0, 0, width, height, 1, 1):
        K[0, :2] /= bin_x
        K[1, 1] /= bin_y
        K[0, 2] = (K[0, 2] - x0 + 0.5) / bin_x - 0.5
        K[1, 2] = (K[1, 2] - y0 + 0.5) / bin_y - 0.5
        width, height = roi_width // bin_x, roi_height // bin_y
        if width == 0 or height == 0:
            raise ValueError(f"camera_info binning {bin_x}x{bin_y} leaves no pixel of its {roi_width}x{roi_height} "
                             "roi; fix the driver's binning")
    for axis, focal, pixels in (("horizontal", K[0, 0], width), ("vertical", K[1, 1], height)):
        fov_deg = float(np.degrees(2.0 * np.arctan2(pixels / 2.0, focal)))
        if not MIN_FOV_DEG <= fov_deg <= MAX_FOV_DEG:
            raise ValueError(f"camera_info K gives a {fov_deg:.3g} degree {axis} field of view (focal length "
                             f"{focal:.4g} px over {pixels} px), outside {MIN_FOV_DEG:g}..{MAX_FOV_DEG:g}: not a "
                             "calibrated camera (an identity K, or focal lengths in mm?); calibrate the camera")
    return K, (width, height)


def scale_intrinsics(K: np.ndarray, src_size: tuple[int, int], dst_size: tuple[int, int]) -> np.ndarray:
    """K for an image resized from src (width, height) to dst (width, height).

    Pixel centres sit at integer coordinates, so the principal point maps as
    c' = (c + 0.5) * s - 0.5 (not c * s, which shifts the image by half a pixel).
    """
    sx = dst_size[0] / src_size[0]
    sy = dst_size[1] / src_size[1]
    out = np.array(K, dtype=np.float64, copy=True)
    out[0, 0] *= sx
    out[0, 1] *= sx
    out[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    out[1, 1] *= sy
    out[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return out


def same_aspect_ratio(size: tuple[int, int], other: tuple[int, int]) -> bool:
    """Whether an image of `size` (width, height) can be one of `other` resized: a resize rounds each
    side to a whole pixel, so its two scales differ by at most that (and by 1% on a tiny image)."""
    scale_x, scale_y = size[0] / other[0], size[1] / other[1]
    return abs(scale_x - scale_y) <= min(1 / other[0] + 1 / other[1], 0.01 * max(scale_x, scale_y))


# a camera's principal point lies within this share of the image's width (height) of its centre: a K whose
# principal point lies further off once scaled than as given was made for the image, not for camera_info's size
PRINCIPAL_POINT_OFF_CENTRE_MAX = 0.15
# ... further off by more than this share: a resize by a few percent moves the principal point by less, and
# either K is as good (the contract's scaling stands, without a word)
PRINCIPAL_POINT_MARGIN = 0.05


def principal_point_off_centre(K: np.ndarray, size: tuple[int, int]) -> float:
    """How far K's principal point lies from the centre of an image of `size` (width, height), as a
    share of its width or height (the larger of the two)."""
    width, height = size
    return max(abs(float(K[0, 2]) - (width - 1) / 2) / width, abs(float(K[1, 2]) - (height - 1) / 2) / height)


def _k_text(K: np.ndarray) -> str:
    return f"fx {K[0, 0]:.4g}, fy {K[1, 1]:.4g}, cx {K[0, 2]:.4g}, cy {K[1, 2]:.4g}"


def intrinsics_text(intrinsics: tuple[np.ndarray, tuple[int, int]]) -> str:
    """`intrinsics_from_camera_info`'s (K, (width, height)) for a message: 'fx .., fy .., cx .., cy .. (WxH)'."""
    K, (width, height) = intrinsics
    return f"{_k_text(K)} ({width}x{height})"


def intrinsics_for_size(K: np.ndarray, info_size: tuple[int, int], image_size: tuple[int, int]
                        ) -> tuple[np.ndarray, str | None]:
    """K of a camera_info of `info_size` (width, height) for an image of `image_size`, and a note when
    the sizes left a choice. The same K when the sizes agree; scaled when the image is the camera_info's
    view resized (the same aspect ratio, to a pixel: a driver's decimation, a camera_info of the
    full-resolution stream); but taken as given, with a note saying so, when its principal point lies
    near the image's centre as given and further off once scaled (a driver that resized its images
    and K but left width and height: scaling would move the principal point off the image's centre
    and shrink the focal lengths). ValueError for another aspect ratio: a crop or another camera,
    whose K cannot be told from this one."""
    if tuple(image_size) == tuple(info_size):
        return K, None
    (width, height), (info_width, info_height) = image_size, info_size
    if not same_aspect_ratio(image_size, info_size):
        raise ValueError(f"depth image {width}x{height}, camera_info {info_width}x{info_height}: another aspect "
                         "ratio (a crop, or another camera's camera_info?); publish the camera_info of this image "
                         "(a crop's: its roi)")
    scaled = scale_intrinsics(K, (info_width, info_height), (width, height))
    as_given = principal_point_off_centre(K, image_size)
    scaled_off = principal_point_off_centre(scaled, image_size)
    if as_given <= PRINCIPAL_POINT_OFF_CENTRE_MAX and scaled_off > as_given + PRINCIPAL_POINT_MARGIN:
        centre = f"({(width - 1) / 2:.4g}, {(height - 1) / 2:.4g})"
        return K, (f"the camera_info says {info_width}x{info_height} but the depth images are {width}x{height} (the "
                   f"same aspect ratio); its K ({_k_text(K)}) has its principal point near the images' centre "
                   f"{centre} as given, while scaled to the images it would be {_k_text(scaled)}, off the centre: K "
                   f"is taken as given, as made for the images, and the camera_info's width and height as wrong. "
                   f"Fix the driver's camera_info (width {width}, height {height}); if its K is in fact that of "
                   f"{info_width}x{info_height} images, publish a camera_info of {width}x{height} with K scaled")
    return scaled, None


def color_for_depth(rgb: np.ndarray, *, depth_size: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """A colour image laid on its depth frame: resized to the frame's (H, W) `shape`. ValueError when
    its aspect ratio differs from the depth image's (`depth_size`, (width, height) as published: the
    frame may be resized to a working size of another aspect ratio): no resize lays it on the depth
    pixels, as it is not registered to them."""
    height, width = rgb.shape[:2]
    if not same_aspect_ratio((width, height), depth_size):
        raise ValueError(f"the colour images are {width}x{height} and the depth images {depth_size[0]}x"
                         f"{depth_size[1]}, another aspect ratio: stretched onto the depth they would colour each "
                         "depth pixel with another point's colour, so its frames are fused without colour. Publish "
                         "colour registered to the depth images (the driver's colour aligned to depth, or depth "
                         "aligned to colour, e.g. a depth_image_proc register node)")
    if rgb.shape[:2] != tuple(shape):
        rgb = resize_rgb(rgb, (shape[1], shape[0]))
    return rgb


def _source_coords(src: int, dst: int) -> np.ndarray:
    """Sample positions in the source image for each destination pixel centre."""
    return (np.arange(dst, dtype=np.float64) + 0.5) * (src / dst) - 0.5


def resize_depth(depth_m: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize of depth to (width, height): never blends across depth edges."""
    height, width = depth_m.shape
    if (width, height) == tuple(size):
        return depth_m
    rows = np.clip(np.rint(_source_coords(height, size[1])), 0, height - 1).astype(np.intp)
    cols = np.clip(np.rint(_source_coords(width, size[0])), 0, width - 1).astype(np.intp)
    return np.ascontiguousarray(depth_m[rows[:, None], cols[None, :]])


def resize_rgb(rgb: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Bilinear resize of an (H, W, 3) uint8 image to (width, height)."""
    height, width = rgb.shape[:2]
    if (width, height) == tuple(size):
        return rgb
    y = np.clip(_source_coords(height, size[1]), 0, height - 1)
    x = np.clip(_source_coords(width, size[0]), 0, width - 1)
    y0 = np.floor(y).astype(np.intp)
    x0 = np.floor(x).astype(np.intp)
    y1 = np.minimum(y0 + 1, height - 1)
    x1 = np.minimum(x0 + 1, width - 1)
    wy = (y - y0)[:, None, None].astype(np.float32)
    wx = (x - x0)[None, :, None].astype(np.float32)
    img = rgb.astype(np.float32)
    top = img[y0][:, x0] * (1 - wx) + img[y0][:, x1] * wx
    bottom = img[y1][:, x0] * (1 - wx) + img[y1][:, x1] * wx
    return np.clip(np.rint(top * (1 - wy) + bottom * wy), 0, 255).astype(np.uint8)
