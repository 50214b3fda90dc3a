"""Bounded error sets: a box of error parameters around the port estimate (docs/physics.md)."""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np


# ----------------------------------------------------------------------------- error set
@dataclass(frozen=True)
class ErrorSet:
    """A box of error parameters ``theta = (dy, dz, t)`` and the controller noise bounds.

    ``port = base_port + [dy, dz]``; ``t`` is the lateral tip load over EI (1/m^2).
    ``noise = (position, angle)`` bounds each measured coordinate of P2's flexion controller.
    """

    base_port: tuple[float, float]
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    noise: tuple[float, float] = (0.0, 0.0)
    samples: int = 5

    @classmethod
    def from_scenario(cls, sc) -> "ErrorSet":
        u = sc.uncertainty
        if u.port_y is None and u.port_z is None:
            base, py, pz = sc.port.position, (0.0, 0.0), (0.0, 0.0)
        else:
            base, py, pz = sc.port.estimate, u.port_y or (0.0, 0.0), u.port_z or (0.0, 0.0)
        tl = u.tip_force_over_ei or (0.0, 0.0)
        noise = (u.sensor_noise.position, u.sensor_noise.angle) if u.sensor_noise else (0.0, 0.0)
        return cls(tuple(base), (py[0], pz[0], tl[0]), (py[1], pz[1], tl[1]), noise, u.samples)

    @property
    def lo_arr(self) -> np.ndarray:
        return np.asarray(self.lo, float)

    @property
    def hi_arr(self) -> np.ndarray:
        return np.asarray(self.hi, float)

    @property
    def active(self) -> np.ndarray:
        """Mask of the uncertain axes (those with a non-degenerate range)."""
        return self.hi_arr > self.lo_arr

    def sample_grid(self, samples: int | None = None) -> np.ndarray:
        """Parameters (n, 3) on a regular grid over the box, ``samples`` per uncertain axis."""
        n = samples or self.samples
        axes = [np.linspace(l, h, n) if h > l else np.array([l]) for l, h in zip(self.lo, self.hi)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)

    def corners(self) -> np.ndarray:
        axes = [(l, h) if h > l else (l,) for l, h in zip(self.lo, self.hi)]
        return np.array(list(itertools.product(*axes)), float)

    def spacing(self, samples: int | None = None) -> np.ndarray:
        n = samples or self.samples
        return (self.hi_arr - self.lo_arr) / (n - 1)

    def port(self, theta: np.ndarray) -> np.ndarray:
        return np.asarray(self.base_port) + theta[..., :2]

    def noise_corners(self) -> np.ndarray:
        """Sensor-noise vectors (c, 6) at the corners of the noise box: [pw(2), pt(2), th_w, th_t]."""
        pos, ang = self.noise
        if pos == 0 and ang == 0:
            return np.zeros((1, 6))
        axes = [(-pos, pos) if pos > 0 else (0.0,)] * 4 + [(-ang, ang) if ang > 0 else (0.0,)] * 2
        return np.array(list(itertools.product(*axes)), float)


