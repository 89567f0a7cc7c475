"""Compile the numba kernels into numba's cache (`__pycache__` beside the sources), as set-up's last
step. Without it the first run of each command compiles them: the node's start-up, the first
replay and the first test session each pay for it.

Runs the engine's warm-up as the node and replay configure it (and with the weighting net's other
evaluation scheme), with a map bound of a few blocks so that eviction and the spill run too (else
they compile at a live node's first eviction); then the mesh decimation, the renderer, the ~/mesh
wire codec and the rvl depth codec, all on tiny inputs. Kernels the cache already holds load in a
fraction of a second, so running it again costs little.
"""
from __future__ import annotations

import logging
import time

import numpy as np


def main() -> None:
    start = time.monotonic()
    from senfunet_core import decimate
    from senfunet_core.engine import SenFuNet
    from senfunet_core.mesher import Mesh
    from senfunet_core.render import default_camera, rasterize
    from senfunet_ros.conversions.rvl import rvl_decode
    from senfunet_ros.conversions.wire import marker_array_cdr, marker_array_from_cdr
    from senfunet_ros.params import Settings, engine_config, engine_weights, expanded_defaults

    logging.getLogger("senfunet").setLevel(logging.ERROR)  # the tiny bound's thrash warning is on purpose here
    settings = Settings.from_values({name: default for name, (default, _) in expanded_defaults().items()})
    for alpha_voxels in ("surface", "surface_voxels"):  # the node's choice, and the engine's other one
        engine = SenFuNet(engine_config(settings, alpha_dtype="float32", feature_dtype="float32", max_blocks=4,
                                        alpha_voxels=alpha_voxels), weights=engine_weights(settings))
        engine.warm_up()
    decimate.warm_up()
    triangle = Mesh(np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], np.float32), np.array([[0, 1, 2]], np.int32),
                    np.full((3, 3), 0.5, np.float32))
    rasterize(triangle, default_camera([triangle], 4 / 3), 32, 24)
    rvl_decode(np.array([1, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0x20, 0x01], np.uint8))  # one pixel of depth 1
    marker_array_from_cdr(marker_array_cdr({(0, 0, 0): triangle}, (), stamp_ns=0, frame_id="map"))
    print(f"senfunet: numba kernels compiled (or loaded from the cache) in {time.monotonic() - start:.1f} s")


if __name__ == "__main__":
    main()
