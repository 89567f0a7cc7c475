"""The DDS transport settings the package brings (Fast DDS, the Jazzy default).

`use_large_shm_profile()` points FASTRTPS_DEFAULT_PROFILES_FILE at `fastdds_profile.xml` (a 64 MB
shared-memory segment per participant instead of 512 KB; the file says why) unless another RMW is
chosen or Fast DDS is configured already. It must run before the process creates its first
participant (`rclpy.init`), since Fast DDS reads the profile then.
"""
from __future__ import annotations

import os
from pathlib import Path

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
