"""DDS transport: the settings the package brings (Fast DDS, the Jazzy default), and publishing
large pre-serialized messages and waiting for readers' acknowledgements without holding the GIL
(librcl's functions through ctypes, which releases it while they run: rclpy's bindings hold it).

`use_large_shm_profile()` points FASTRTPS_DEFAULT_PROFILES_FILE at `fastdds_profile.xml` (a 64 MB
shared-memory segment per participant instead of 512 KB; the file says why) unless another RMW is
chosen or Fast DDS is configured already. It must run before the process creates its first
participant (`rclpy.init`), since Fast DDS reads the profile then.
"""
from __future__ import annotations

import ctypes
import functools
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


# librcl's functions used here, with their argument types (all return an rcl_ret_t)
_SIGNATURES = {
    "rcl_publish_serialized_message": (ctypes.c_void_p, ctypes.POINTER(_SerializedMessage), ctypes.c_void_p),
    "rcl_publisher_wait_for_all_acked": (ctypes.c_void_p, ctypes.c_int64),  # timeout in ns
}
_RCL_RET_OK, _RCL_RET_TIMEOUT, _RCL_RET_UNSUPPORTED = 0, 2, 3


@functools.cache  # resolved on first use
def _rcl(name: str) -> Callable | None:
    """librcl's function `name` through ctypes, or None when librcl cannot be found."""
    import rclpy

    for candidate in (Path(rclpy.__file__).resolve().parents[3] / "librcl.so", "librcl.so"):
        try:
            function = getattr(ctypes.CDLL(str(candidate)), name)
        except (OSError, AttributeError):
            continue
        function.argtypes, function.restype = _SIGNATURES[name], ctypes.c_int
        return function
    return None


def publish_serialized(publisher: Any, data: np.ndarray) -> None:
    """Publish CDR bytes held in a uint8 numpy array without a copy and without holding the GIL
    (rclpy's publish of bytes holds it for the whole copy into DDS: for a 100 MB mesh message, a
    few hundred milliseconds in which the node's other threads cannot run any Python). Falls back
    to `publisher.publish(bytes)` where librcl is not reachable."""
    function = _rcl("rcl_publish_serialized_message")
    data = np.ascontiguousarray(data, np.uint8)
    if function is None:
        publisher.publish(data.tobytes())
        return
    message = _SerializedMessage(data.ctypes.data, data.nbytes, data.nbytes, None, None, None, None, None)
    with publisher.handle:  # keeps the publisher alive during the call
        ret = function(publisher.handle.pointer, ctypes.byref(message), None)
    if ret != 0:
        raise RuntimeError(f"rcl_publish_serialized_message failed (rcl_ret_t {ret}) on {publisher.topic_name}")


def wait_for_all_acked(publisher: Any, timeout_s: float) -> bool:
    """Block until every reader of a reliable publisher acknowledged its samples (True) or timeout_s
    passed (False), without holding the GIL: rclpy's `Publisher.wait_for_all_acked` holds it for as
    long as it blocks, which stops every other Python thread of the process (integration, the
    subscriptions). A middleware that cannot tell counts as acknowledged. Falls back to rclpy's wait
    where librcl is not reachable."""
    timeout_ns = max(0, int(timeout_s * 1e9))
    function = _rcl("rcl_publisher_wait_for_all_acked")
    if function is None:
        from rclpy.duration import Duration

        return bool(publisher.wait_for_all_acked(Duration(nanoseconds=timeout_ns)))
    with publisher.handle:  # keeps the publisher alive during the call
        ret = function(publisher.handle.pointer, timeout_ns)
    if ret not in (_RCL_RET_OK, _RCL_RET_TIMEOUT, _RCL_RET_UNSUPPORTED):
        raise RuntimeError(f"rcl_publisher_wait_for_all_acked failed (rcl_ret_t {ret}) on {publisher.topic_name}")
    return ret != _RCL_RET_TIMEOUT


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
