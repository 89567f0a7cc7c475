"""The two simulated depth sensors: a ToF camera (Kinect-style noise after Handa et al., scaled as
in the paper, flying pixels, dropouts, multipath, dark materials) and a stereo pair (OpenCV
StereoSGBM on rendered, noisy images). Depth is z-depth, float32, 0 = invalid."""
from __future__ import annotations

import cv2
import numpy as np

from .raycast import _translation, intrinsics_scaled, render_view
from .scenes import Scene

SENSORS = ("tof", "stereo")
STEREO_BASELINE_M = 0.1  # right camera sits +0.1 m along the left camera's x axis
TOF_OFFSET_X_M = -0.05  # ToF optical frame relative to the stereo left camera, along its x axis
TOF_RANGE_M = (0.2, 5.0)
KINECT_BF = 35130.0  # Handa et al.: disparity [px] = 35130 / depth [mm]
SGBM_BLOCK_SIZE = 5  # small block: keeps thin furniture parts; P1/P2 follow OpenCV's 8*bs^2, 32*bs^2
SGBM_NUM_DISPARITIES = 64
MULTIPATH_RANGE_M = 0.08  # the ToF multipath overestimate decays as exp(-distance to the other surface / this)


def _tof_depth(view: dict, K: np.ndarray, scene: Scene, rng: np.random.Generator) -> np.ndarray:
    """Kinect-style noise (Handa et al., scaled) on a true z-depth image; 0 = invalid.

    On top of Handa's model: multipath (depth overestimated near concave corners, when the view
    holds `other_distance_m`), noise growing as 1 / sqrt(infrared reflectivity) (dark materials are
    several times noisier) and dropouts where the return reflectivity * cos / z^2 is too weak."""
    z = view["depth_m"].astype(np.float32)
    h, w = z.shape
    cosi = view["cos_incidence"]
    reflectivity = np.array([sf.ir_reflectivity for sf in scene.surfaces], np.float32)[view["surface_id"]]
    if scene.tof_multipath_m > 0 and "other_distance_m" in view:
        z = z + np.float32(scene.tof_multipath_m) * np.exp(-view["other_distance_m"] / np.float32(MULTIPATH_RANGE_M))
    # pixel shuffling: each pixel reads the true depth at a Gaussian-shifted location
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    su = u + rng.normal(0, scene.tof_shuffle_px, (h, w)).astype(np.float32)
    sv = v + rng.normal(0, scene.tof_shuffle_px, (h, w)).astype(np.float32)
    zs = cv2.remap(z, su, sv, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    cs = cv2.remap(cosi, su, sv, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    rs = cv2.remap(reflectivity, su, sv, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    # flying pixels: near depth discontinuities take a value between fore- and background
    kernel = np.ones((3, 3), np.uint8)
    zmax = cv2.dilate(zs, kernel)
    zmin = cv2.erode(zs, kernel)
    edge = (zmax - zmin) > (0.05 + 0.05 * zs)
    fly = edge & (rng.random((h, w)) < scene.tof_flying_fraction)
    zs = np.where(fly, zmin + rng.random((h, w)).astype(np.float32) * (zmax - zmin), zs)
    # disparity noise and 1/8 px quantisation: error grows ~ z^2
    disp = KINECT_BF / (np.maximum(zs, 1e-3) * 1000.0)
    noise_gain = np.clip(np.sqrt(0.5 / np.maximum(rs, 1e-3)), 0.8, 4.0)  # 1 at reflectivity 0.5
    disp = disp + rng.normal(0, scene.tof_noise_scale / 6.0, (h, w)) * noise_gain
    disp = np.round(disp * 8.0) / 8.0
    with np.errstate(divide="ignore"):
        zn = np.where(disp > 0, KINECT_BF / np.maximum(disp, 1e-6) / 1000.0, 0.0)
    # dropouts: grazing angles (more likely the flatter), random speckles, out of range
    graze = (cs < scene.tof_grazing_cos) | ((cs < 2 * scene.tof_grazing_cos) & (rng.random((h, w)) < 0.3))
    speckle = rng.random((h, w)) < scene.tof_speckle_fraction
    weak = rs * cs < scene.tof_min_signal * zs * zs
    bad = graze | speckle | weak | (zn < TOF_RANGE_M[0]) | (zn > TOF_RANGE_M[1]) | (disp <= 0)
    return np.where(bad, 0.0, zn).astype(np.float32)


def _stereo_grey(view: dict, scene: Scene, rng: np.random.Generator, width: int, height: int) -> tuple:
    """2x render -> area downsample (antialias) -> rgb and noisy greyscale."""
    rgb = cv2.resize(view["rgb"], (width, height), interpolation=cv2.INTER_AREA)
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    grey += rng.normal(0, scene.stereo_image_noise, grey.shape).astype(np.float32)
    return rgb, np.clip(np.round(grey), 0, 255).astype(np.uint8)


def _sgbm(scene: Scene) -> cv2.StereoSGBM:
    bs = SGBM_BLOCK_SIZE
    return cv2.StereoSGBM.create(minDisparity=0, numDisparities=SGBM_NUM_DISPARITIES, blockSize=bs,
                                 P1=8 * bs * bs, P2=32 * bs * bs, disp12MaxDiff=1, preFilterCap=31,
                                 uniquenessRatio=scene.stereo_uniqueness,
                                 speckleWindowSize=scene.stereo_speckle_window, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_HH)


def _stereo_depth(scene: Scene, T_left: np.ndarray, K: np.ndarray, width: int, height: int,
                  rng: np.random.Generator, sgbm: cv2.StereoSGBM) -> tuple[np.ndarray, np.ndarray]:
    K2 = intrinsics_scaled(K, 2)
    T_right = T_left @ _translation(STEREO_BASELINE_M, 0, 0)
    left = render_view(scene, T_left, K2, 2 * width, 2 * height)
    right = render_view(scene, T_right, K2, 2 * width, 2 * height)
    rgb_l, g_l = _stereo_grey(left, scene, rng, width, height)
    _, g_r = _stereo_grey(right, scene, rng, width, height)
    disp = sgbm.compute(g_l, g_r).astype(np.float32) / 16.0
    with np.errstate(divide="ignore"):
        depth = np.where(disp > 0, K[0, 0] * STEREO_BASELINE_M / np.maximum(disp, 1e-6), 0.0)
    return depth.astype(np.float32), rgb_l


def simulate_tof_depth(scene: Scene, T_world_camera: np.ndarray, K: np.ndarray, width: int, height: int,
                       rng: np.random.Generator) -> np.ndarray:
    """One ToF depth image (H,W) float32 (0 = invalid) seen from the ToF optical frame pose."""
    view = render_view(scene, T_world_camera, K, width, height, with_rgb=False,
                       with_other_distance=scene.tof_multipath_m > 0)
    return _tof_depth(view, K, scene, rng)


def simulate_stereo_depth(scene: Scene, T_world_camera: np.ndarray, K: np.ndarray, width: int, height: int,
                          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One SGBM depth image (H,W) float32 (0 = invalid) and the left rgb, from the left camera pose."""
    return _stereo_depth(scene, np.asarray(T_world_camera, np.float64), K, width, height, rng, _sgbm(scene))
