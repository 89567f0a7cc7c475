"""The device's walk through a scene: its pose as a smooth function of time."""
from __future__ import annotations

import numpy as np

from .scenes import Scene


class Trajectory:
    """Device (= stereo left optical frame) pose as a smooth function of time.

    Walks the scene's corridor loop at 0.1-0.85 m/s (slowing in tight turns so the path turns at
    most ~20 deg/s), looking sideways into the room with a slowly varying yaw offset, at 1.5 m
    (+- ~0.15), pitched ~10-25 deg down. Dense 2 ms samples, linearly interpolated.
    """

    def __init__(self, scene: Scene, seed: int, t0: float, t1: float):
        rng = np.random.default_rng([seed, 2])
        loop = np.asarray(scene.corridor_xy_m)
        seg = np.linalg.norm(np.roll(loop, -1, 0) - loop, axis=1)
        s_knots = np.concatenate([[0], np.cumsum(seg)])
        length = s_knots[-1]
        loop_c = np.vstack([loop, loop[:1]])
        step = np.diff(loop_c, axis=0)  # segment i: knot i -> knot i+1
        hk = np.unwrap(np.arctan2(step[:, 1], step[:, 0]))
        heading = np.append(hk, hk[-1] + (np.angle(np.exp(1j * (hk[0] - hk[-1])))))  # close the loop
        kappa = np.abs(np.gradient(heading, s_knots))
        self.dt = 0.002
        # always start at a fixed time, so the pose at a stamp does not depend on the window asked for
        start = min(t0, -1.0)
        self.t = np.arange(start, t1 + 0.25 + self.dt, self.dt)
        n = len(self.t)
        tt = self.t

        def smooth(amp: float, fmin: float, fmax: float, k: int = 3) -> np.ndarray:
            out = np.zeros(n)
            for _ in range(k):
                out += np.sin(2 * np.pi * rng.uniform(fmin, fmax) * tt + rng.uniform(0, 2 * np.pi))
            return amp * out / k

        v0 = rng.uniform(0.5, 0.8)
        speed = np.clip(v0 + smooth(0.5, 0.03, 0.12), 0.1, 0.85)  # walking with slow scanning phases
        direction = 1.0 if rng.random() < 0.5 else -1.0
        s = np.empty(n)
        s[0] = rng.uniform(0, length)
        max_turn = np.deg2rad(35.0) * 0.6
        for i in range(1, n):  # 1 scalar op per 2 ms sample; cheap
            k = np.interp(s[i - 1] % length, s_knots, kappa)
            vi = min(speed[i], max_turn / max(k, 1e-6))
            s[i] = s[i - 1] + direction * vi * self.dt
        sm = np.mod(s, length)
        x = np.interp(sm, s_knots, loop_c[:, 0])
        y = np.interp(sm, s_knots, loop_c[:, 1])
        hd = np.interp(sm, s_knots, heading) + (0 if direction > 0 else np.pi)
        # unwrap the path heading over time (the loop closes with a 2 pi jump)
        hd = np.unwrap(hd)
        # lateral wobble off the loop (small: stays in the corridor)
        lat = smooth(0.08, 0.05, 0.2)
        x = x + lat * -np.sin(hd)
        y = y + lat * np.cos(hd)
        side = rng.choice([-1.0, 1.0])  # look to the inside or the outside of the loop, swinging between
        yaw_off = side * np.deg2rad(rng.uniform(20, 70)) + smooth(np.deg2rad(80), 0.04, 0.12)
        yaw = hd + yaw_off
        yaw = np.convolve(np.pad(yaw, 50, mode="edge"), np.ones(101) / 101, "valid")  # 0.2 s smoothing
        z = 1.5 + smooth(0.15, 0.02, 0.1) + 0.01 * np.sin(2 * np.pi * 1.8 * tt)  # slow + step bob
        pitch = np.deg2rad(-15.0) + smooth(np.deg2rad(8), 0.03, 0.12)
        roll = smooth(np.deg2rad(2), 0.05, 0.2)
        self.pos = np.stack([x, y, z], 1)
        self.ang = np.stack([yaw, pitch, roll], 1)

    def __call__(self, stamps_s: np.ndarray) -> np.ndarray:
        """(M,4,4) poses of the device at stamps_s."""
        st = np.atleast_1d(np.asarray(stamps_s, float))
        pos = np.stack([np.interp(st, self.t, self.pos[:, i]) for i in range(3)], 1)
        yaw, pitch, roll = (np.interp(st, self.t, self.ang[:, i]) for i in range(3))
        fwd = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], 1)
        right = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], 1)
        down = np.cross(fwd, right)
        # roll about the forward axis
        cr, sr = np.cos(roll)[:, None], np.sin(roll)[:, None]
        x_ax = cr * right + sr * down
        y_ax = -sr * right + cr * down
        T = np.tile(np.eye(4), (len(st), 1, 1))
        T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x_ax, y_ax, fwd, pos
        return T
