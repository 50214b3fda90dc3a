"""The settings of a gain schedule (:class:`GainOptions`) and its results (:class:`Segment`,
:class:`GainSchedule`, with ``to_json()`` the plan JSON's ``gains`` entries)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import ErrplanError

@dataclass(frozen=True)
class GainOptions:
    """Settings of the gain schedule (SI).

    ``max_segment``: longest segment the path is cut into before certification (m); bounds the
    jump the quasi-static controller makes per step. ``switch_tolerance``: the controller moves on
    to the next waypoint once within this distance (m); ``tolerance``: final convergence (m).
    ``margin``: certified segments satisfy ``rho_s <= 1 - margin`` in the optimiser.
    ``max_gain_change``: bound on ``|k_{s+1} - k_s|`` (soft, penalised slack).
    Optimiser sample: ``opt_disk`` + ``opt_ring`` tips per ball, ``opt_samples`` per uncertain axis.
    Verification sample: ``verify_disk`` + ``verify_ring`` tips, ``verify_samples`` per axis,
    ``verify_refine`` halvings of the local search over instances and tips.
    """

    margin: float = 0.02
    max_segment: float = 0.02
    switch_tolerance: float = 1e-3
    tolerance: float = 1e-5
    max_gain_change: float = 0.2
    max_depth: int = 6
    min_segment: float = 2e-4
    rounds: int = 4
    opt_disk: int = 40
    opt_ring: int = 24
    opt_samples: int = 3
    verify_disk: int = 200
    verify_ring: int = 72
    verify_samples: int = 6
    verify_refine: int = 4
    slack_weight: float = 1e3

    @classmethod
    def for_dim(cls, dim: int, **overrides) -> "GainOptions":
        """Defaults for the plane (the dataclass defaults) or for 3-D, where balls and error sets
        are larger: fewer tips and samples per axis, the same local refinement."""
        kw = dict(SPATIAL_DEFAULTS) if dim == 3 else {}
        kw.update(overrides)
        return cls(**kw)

    def validate(self) -> "GainOptions":
        for name in ("max_segment", "switch_tolerance", "tolerance", "min_segment"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ErrplanError(f"gain option {name} = {v!r}: expected a length > 0 m")
        if not 0 <= self.margin < 1:
            raise ErrplanError(f"gain option margin = {self.margin!r}: expected a number in [0, 1)")
        if not self.max_gain_change > 0:
            raise ErrplanError(f"gain option max_gain_change = {self.max_gain_change!r}: expected > 0")
        for name in ("opt_samples", "verify_samples"):
            if getattr(self, name) < 2:
                raise ErrplanError(f"gain option {name} = {getattr(self, name)!r}: expected >= 2")
        return self


#: GainOptions defaults in 3-D (GainOptions.for_dim)
SPATIAL_DEFAULTS = {"opt_disk": 30, "opt_ring": 26, "opt_samples": 2,
                    "verify_disk": 90, "verify_ring": 40, "verify_samples": 3}


@dataclass
class Segment:
    """One certified (or not) segment: the controller aims at ``end`` from ``start`` with ``gain``."""

    start: np.ndarray
    end: np.ndarray
    gain: float
    certified_G_norm: float      # verified worst-case ||G|| over the ball and the error set
    step_ratio: float            # verified worst nonlinear one-step ratio |x' - b| / |x - b|
    certified: bool
    radius: float                # ball radius, m
    predicted_G_norm: float      # the optimiser's rho_s at its (coarser) sample
    edge: int                    # index of the path edge this segment belongs to
    depth: int = 0               # halvings applied to reach it
    samples: dict = field(default_factory=dict)
    reason: str = ""
    ball_clearance: float | None = None  # m: a lower bound on the robust clearance of every tip of the ball

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.end - self.start))

    def to_json(self) -> dict:
        out = {"from": [float(v) for v in self.start], "to": [float(v) for v in self.end],
               "gain": float(self.gain), "certified_G_norm": _finite(self.certified_G_norm),
               "certified": bool(self.certified), "step_ratio": _finite(self.step_ratio),
               "radius": float(self.radius), "predicted_G_norm": _finite(self.predicted_G_norm),
               "edge": int(self.edge), "depth": int(self.depth), "samples": self.samples}
        if not self.certified and out["certified_G_norm"] is not None and out["certified_G_norm"] < 1:
            # ||G|| < 1 over the ball, but a full step leaves the ball (or the workspace): the worst case
            # over every tip the controller can visit is not bounded by it, so it is no certificate
            # (docs/interfaces.md: certified_G_norm < 1 means certified). The ball's value stays here:
            out["ball_G_norm"] = out["certified_G_norm"]
            out["certified_G_norm"] = None
        if self.ball_clearance is not None:
            out["ball_clearance"] = float(self.ball_clearance)
        if self.reason:
            out["reason"] = self.reason
        return out


def _finite(v: float) -> float | None:
    """JSON-safe number: an unbounded worst case is reported as null (never as certified)."""
    return float(v) if math.isfinite(v) else None


@dataclass
class GainSchedule:
    """The segments of one path with their gains and verified certificates."""

    path: np.ndarray
    segments: list[Segment]
    options: GainOptions
    solver: dict = field(default_factory=dict)

    @property
    def certified(self) -> bool:
        return bool(self.segments) and all(s.certified for s in self.segments)

    @property
    def waypoints(self) -> np.ndarray:
        return np.array([s.end for s in self.segments])

    @property
    def gains(self) -> np.ndarray:
        return np.array([s.gain for s in self.segments])

    @property
    def max_certified_G_norm(self) -> float:
        return max((s.certified_G_norm for s in self.segments), default=float("nan"))

    def predicted_steps(self) -> float:
        """Sum over segments of ``log(R / tol) / -log(||G||)`` (inf if a segment is uncertified)."""
        tot = 0.0
        for i, s in enumerate(self.segments):
            tol = self.options.tolerance if i == len(self.segments) - 1 else self.options.switch_tolerance
            if not s.certified_G_norm < 1:
                return float("inf")
            tot += max(math.log(s.radius / tol), 0.0) / max(-math.log(max(s.certified_G_norm, 1e-12)), 1e-12)
        return tot

    def to_json(self) -> list[dict]:
        return [s.to_json() for s in self.segments]

    def summary(self) -> dict:
        return {"segments": len(self.segments), "certified": self.certified,
                "uncertified": sum(not s.certified for s in self.segments),
                "max_certified_G_norm": _finite(self.max_certified_G_norm),
                "max_step_ratio": _finite(max((s.step_ratio for s in self.segments), default=float("nan"))),
                "gain_range": [float(self.gains.min()), float(self.gains.max())] if self.segments else [],
                "predicted_steps": _finite(self.predicted_steps()), "solver": self.solver}
