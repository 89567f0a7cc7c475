"""DDS transport: the settings the package brings (Fast DDS, the Jazzy default), and publishing
large pre-serialized messages without holding the GIL.

`use_large_shm_profile()` points FASTRTPS_DEFAULT_PROFILES_FILE at `fastdds_profile.xml` (a 64 MB
shared-memory segment per participant instead of 512 KB; the file says why) unless another RMW is
chosen or Fast DDS is configured already. It must run before the process creates its first
participant (`rclpy.init`), since Fast DDS reads the profile then.
"""
from __future__ import annotations

import ctypes
import os
from pathlib import Path
from typing import Any
from collections.abc import Callable

import numpy as np

PROFILE = Path(__file__).resolve().with_name("fastdds_profile.xml")
_USER_SETTINGS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE", "FASTDDS_BUILTIN_TRANSPORTS",
                  "RMW_FASTRTPS_USE_QOS_FROM_XML", "SKIP_DEFAULT_XML_FILE")


def use_large_shm_profile(environ: dict[str, str] | None = None) -> Path | None:
    """Set FASTRTPS_DEFAULT_PROFILES_FILE to PROFILE in `environ` (default: this process) unless
    another RMW is chosen or Fast DDS is configured (env, or a DEFAULT_FASTRTPS_PROFILES.xml in the
    working directory). Returns the profile's path when it was set."""
    env = os.environ if environ is None else environ
    if env.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") not in ("rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp"):
        return None
    if any(env.get(name) for name in _USER_SETTINGS) or Path("DEFAULT_FASTRTPS_PROFILES.xml").exists():
        return None
    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(PROFILE)
    return PROFILE


class _SerializedMessage(ctypes.Structure):
    """rcl_serialized_message_t (rcutils_uint8_array_t): buffer, length, capacity, allocator."""

    _fields_ = [("buffer", ctypes.c_void_p), ("buffer_length", ctypes.c_size_t), ("buffer_capacity", ctypes.c_size_t),
                ("allocate", ctypes.c_void_p), ("deallocate", ctypes.c_void_p), ("reallocate", ctypes.c_void_p),
                ("zero_allocate", ctypes.c_void_p), ("state", ctypes.c_void_p)]


def _rcl_publish() -> Callable | None:
    """rcl_publish_serialized_message through ctypes (which releases the GIL while it runs), or
    None when librcl cannot be found."""
    import rclpy

    candidates = [Path(rclpy.__file__).resolve().parents[3] / "librcl.so", "librcl.so"]
    for candidate in candidates:
        try:
            function = ctypes.CDLL(str(candidate)).rcl_publish_serialized_message
        except (OSError, AttributeError):
            continue
        function.argtypes = (ctypes.c_void_p, ctypes.POINTER(_SerializedMessage), ctypes.c_void_p)
        function.restype = ctypes.c_int
        return function
    return None


_PUBLISH: list[Callable | None] = []  # resolved on first use


def publish_serialized(publisher: Any, data: np.ndarray) -> None:
    """Publish CDR bytes held in a uint8 numpy array without a copy and without holding the GIL
    (rclpy's publish of bytes holds it for the whole copy into DDS: for a 100 MB mesh message, a
    few hundred milliseconds in which the node's other threads cannot run any Python). Falls back
    to `publisher.publish(bytes)` where librcl is not reachable."""
    if not _PUBLISH:
        _PUBLISH.append(_rcl_publish())
    function = _PUBLISH[0]
    data = np.ascontiguousarray(data, np.uint8)
    if function is None:
        publisher.publish(data.tobytes())
        return
    message = _SerializedMessage(data.ctypes.data, data.nbytes, data.nbytes, None, None, None, None, None)
    with publisher.handle:  # keeps the publisher alive during the call
        ret = function(publisher.handle.pointer, ctypes.byref(message), None)
    if ret != 0:
        raise RuntimeError(f"rcl_publish_serialized_message failed (rcl_ret_t {ret}) on {publisher.topic_name}")


def shut_down_rclpy() -> None:
    """rclpy.try_shutdown, which a signal can race: rclpy's signal handler shuts the context down from
    its own thread, between try_shutdown's check and its shutdown (then rcl says it was shut down)."""
    import rclpy
    from rclpy._rclpy_pybind11 import RCLError

    try:
        rclpy.try_shutdown()
    except RCLError:
        if rclpy.ok():
            raise
