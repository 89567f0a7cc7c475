"""Dataset folders: a recording's frames, pose streams, scene description and GT mesh as files."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .geometry import gt_mesh
from .scenes import _scene_from_json, _scene_to_json
from .sensors import SENSORS
from .sequences import SensorFrame, Sequence


def write_dataset(seq: Sequence, folder: str | Path, *, gt_voxel_size_m: float = 0.02) -> None:
    """Write scene.json, <sensor>.npz (frames), poses_<sensor>.npz and gt_mesh.npz into folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scene.json").write_text(_scene_to_json(seq.scene))
    for sensor in SENSORS:
        fr = [f for f in seq.frames if f.sensor == sensor]
        arrays: dict[str, Any] = {  # Any: numpy's stub of savez_compressed types **kwds as its own options
            "stamp_s": np.array([f.stamp_s for f in fr], np.float64),
            "depth_m": np.stack([f.depth_m for f in fr]).astype(np.float32) if fr else np.zeros((0, 0, 0), np.float32),
            "K": np.stack([f.K for f in fr]) if fr else np.zeros((0, 3, 3)),
            "T_world_camera": np.stack([f.T_world_camera for f in fr]) if fr else np.zeros((0, 4, 4)),
        }
        rgbs = [f.rgb for f in fr if f.rgb is not None]
        if fr and len(rgbs) == len(fr):
            arrays["rgb"] = np.stack(rgbs).astype(np.uint8)
        np.savez_compressed(folder / f"{sensor}.npz", **arrays)
        if sensor in seq.pose_stamps_s:
            np.savez_compressed(folder / f"poses_{sensor}.npz", stamp_s=seq.pose_stamps_s[sensor],
                                T_world_camera=seq.pose_T_world_camera[sensor])
    mesh = gt_mesh(seq.scene, gt_voxel_size_m)
    np.savez_compressed(folder / "gt_mesh.npz", vertices=mesh.vertices, faces=mesh.faces)


def load_dataset(folder: str | Path) -> Sequence:
    """Inverse of write_dataset (the GT mesh is read separately: np.load(folder / 'gt_mesh.npz'))."""
    folder = Path(folder)
    scene = _scene_from_json((folder / "scene.json").read_text())
    seq = Sequence(scene=scene)
    frames = []
    for sensor in SENSORS:
        path = folder / f"{sensor}.npz"
        if path.exists():
            with np.load(path) as z:  # each array read once (indexing the NpzFile re-reads it)
                arrays = {k: z[k] for k in z.files}
            rgb = arrays.get("rgb")
            for i in range(len(arrays["stamp_s"])):
                frames.append(SensorFrame(sensor, float(arrays["stamp_s"][i]), arrays["depth_m"][i],
                                          None if rgb is None else rgb[i], arrays["K"][i],
                                          arrays["T_world_camera"][i]))
        ppath = folder / f"poses_{sensor}.npz"
        if ppath.exists():
            with np.load(ppath) as z:
                seq.pose_stamps_s[sensor] = z["stamp_s"]
                seq.pose_T_world_camera[sensor] = z["T_world_camera"]
    frames.sort(key=lambda f: f.stamp_s)
    seq.frames = frames
    return seq
