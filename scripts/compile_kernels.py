"""Compile the numba kernels into numba's cache (`__pycache__` beside the sources), as set-up's last
step. Without it the first run of each command compiles them: the node's start-up, the first
replay and the first test session each pay for it.

Runs the engine's warm-up as the node and replay configure it (and with the weighting net's other
evaluation scheme), with a map bound of a few blocks so that eviction and the spill run too (else
they compile at a live node's first eviction) and the weight cloud's kernel for each; then the mesh
decimation, the renderer, the ~/mesh wire codec and the rvl depth codec, all on tiny inputs. Kernels
the cache already holds load in a fraction of a second, so running it again costs little.

numba renews a cached kernel only when its own file changes, yet kernels inline functions of other
modules (integration's kernels inline the grid's): after any change of the sources (a `git pull`),
every cached kernel is dropped first (`drop_stale_caches`), so none runs code that is gone.
"""
from __future__ import annotations

import hashlib
import logging
import time
from pathlib import Path

import numpy as np

STAMP = "numba_sources.sha256"  # in the first package's __pycache__: the sources the caches were built from


def sources_digest(roots: list[Path]) -> str:
    digest = hashlib.sha256()
    for root in roots:
        for path in sorted(root.rglob("*.py")):
            digest.update(str(path.relative_to(root.parent)).encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def drop_stale_caches(roots: list[Path]) -> str | None:
    """Delete numba's cache files under these package folders unless they were built from the sources
    there now; the digest to stamp once the kernels are compiled (None: the caches are current)."""
    digest = sources_digest(roots)
    stamp = roots[0] / "__pycache__" / STAMP
    if stamp.is_file() and stamp.read_text().strip() == digest:
        return None
    dropped = [path for root in roots for pattern in ("__pycache__/*.nbi", "__pycache__/*.nbc")
               for path in root.rglob(pattern)]
    for path in dropped:
        path.unlink(missing_ok=True)
    if dropped:
        print(f"senfunet: the sources changed since the numba kernels were cached: {len(dropped)} cache files "
              "dropped, compiling again")
    return digest


def main() -> None:
    start = time.monotonic()
    import senfunet_core
    import senfunet_ros

    roots = [Path(package.__file__).parent for package in (senfunet_core, senfunet_ros)]
    digest = drop_stale_caches(roots)
    from senfunet_core import decimate, readout
    from senfunet_core.engine import SenFuNet, warm_up
    from senfunet_core.mesher import Mesh
    from senfunet_core.render import default_camera, rasterize
    from senfunet_ros.conversions.rvl import rvl_decode
    from senfunet_ros.conversions.wire import marker_array_cdr, marker_array_from_cdr
    from senfunet_ros.params import Settings, engine_config, engine_weights, expanded_defaults

    logging.getLogger("senfunet").setLevel(logging.ERROR)  # the tiny bound's thrash warning is on purpose here
    settings = Settings.from_values({name: default for name, (default, _) in expanded_defaults().items()})
    # the node's configuration (its weighting net's arithmetic: int8 or bfloat16 where the CPU has them,
    # whose windows' kernels are their own), replay's (float32, with --compare's TSDF Fusion) and the engine's
    # other evaluation scheme
    for overrides in ({}, {"alpha_dtype": "float32", "feature_dtype": "float32", "tsdf_fusion": True},
                      {"alpha_dtype": "float32", "feature_dtype": "float32", "alpha_voxels": "surface_voxels"}):
        engine = SenFuNet(engine_config(settings, max_blocks=4, **overrides), weights=engine_weights(settings))
        warm_up(engine)
        readout.warm_up(engine)
    decimate.warm_up()
    triangle = Mesh(np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], np.float32), np.array([[0, 1, 2]], np.int32),
                    np.full((3, 3), 0.5, np.float32))
    rasterize(triangle, default_camera([triangle], 4 / 3), 32, 24)
    rvl_decode(np.array([1, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0x20, 0x01], np.uint8))  # one pixel of depth 1
    marker_array_from_cdr(marker_array_cdr({(0, 0, 0): triangle}, (), stamp_ns=0, frame_id="map"))
    if digest is not None:
        (roots[0] / "__pycache__").mkdir(exist_ok=True)
        (roots[0] / "__pycache__" / STAMP).write_text(digest + "\n")
    print(f"senfunet: numba kernels compiled (or loaded from the cache) in {time.monotonic() - start:.1f} s")


if __name__ == "__main__":
    main()
