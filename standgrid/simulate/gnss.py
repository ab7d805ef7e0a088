"""Simulated GNSS fixes under canopy and IMU samples along a true trajectory."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from standgrid.geometry import Matrix4
from standgrid.mission.sensors import FixQuality, GnssFixes, ImuSamples
from standgrid.simulate.chain import FrameChain

GRAVITY = 9.80665


@dataclass(frozen=True)
class GnssModel:
    """Fix rate, canopy noise, RTK windows, dropouts and multipath outliers."""

    rate_hz: float = 2.0
    canopy_h_std: tuple[float, float] = (0.5, 3.0)
    rtk_h_std: tuple[float, float] = (0.02, 0.03)
    rtk_windows: int = 3
    rtk_window_s: tuple[float, float] = (15.0, 40.0)
    dropouts: int = 3
    dropout_s: tuple[float, float] = (8.0, 25.0)
    outlier_fraction: float = 0.02
    outlier_m: tuple[float, float] = (10.0, 40.0)
    #: Open sky: every fix RTK fixed with ``rtk_h_std`` noise (outliers included).
    open_sky: bool = False
    #: Horizontal RMS (m) of one bias drawn per recording (0: none), added to every fix.
    bias_h_m: float = 0.0
    #: Horizontal RMS (m) of a first-order Gauss-Markov error (multipath under a canopy)
    #: with correlation time ``walk_tau_s`` (0: none), added to every fix.
    walk_h_m: float = 0.0
    walk_tau_s: float = 120.0
    #: The horizontal accuracy the receiver states for every non-RTK fix (None: the true
    #: white-noise sigma); under a canopy receivers state far less than the real error.
    stated_h_m: float | None = None
    #: Share of the non-RTK fixes flagged RTK float (the rest: DGPS 40 %, single).
    float_share: float = 0.0

    def __post_init__(self) -> None:
        if not self.walk_tau_s > 0:
            raise ValueError(f"walk_tau_s must be positive, got {self.walk_tau_s}")
        for name in ("bias_h_m", "walk_h_m", "float_share"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")

    @classmethod
    def under_canopy(cls) -> GnssModel:
        """GNSS as under a forest canopy: 0.3 m white noise, a Gauss-Markov walk of 2 m over
        120 s, a 1 m bias per recording, RTK float or single fixes stating 0.5 m, no RTK
        fixed windows, 2 % multipath outliers."""
        return cls(
            canopy_h_std=(0.3, 0.3),
            rtk_windows=0,
            bias_h_m=1.0,
            walk_h_m=2.0,
            walk_tau_s=120.0,
            stated_h_m=0.5,
            float_share=0.5,
        )


#: ``standgrid simulate --gnss``: the models by name.
GNSS_MODELS = ("demo", "canopy")


def gnss_model(name: str) -> GnssModel:
    """The GNSS model called ``name`` (:data:`GNSS_MODELS`)."""
    if name == "demo":
        return GnssModel()
    if name == "canopy":
        return GnssModel.under_canopy()
    raise ValueError(f"GNSS model must be one of {', '.join(GNSS_MODELS)}, got {name!r}")


@dataclass(frozen=True, eq=False)
class SimulatedGnss:
    """Fixes as written, plus the truth: true antenna positions (CRS) and outlier flags."""

    fixes: GnssFixes
    true_xyz: NDArray[np.float64]
    outlier: NDArray[np.bool_]


def _windows(
    rng: np.random.Generator, t0: float, t1: float, count: int, length: tuple[float, float]
) -> NDArray[np.float64]:
    starts = rng.uniform(t0, max(t0, t1 - length[1]), count)
    return np.column_stack([starts, starts + rng.uniform(*length, count)])


def _in_windows(t: NDArray[np.float64], windows: NDArray[np.float64]) -> NDArray[np.bool_]:
    out = np.zeros(len(t), dtype=bool)
    for a, b in windows:
        out |= (t >= a) & (t < b)
    return out


def interpolate_positions(
    node_ns: NDArray[np.int64], node_xyz: NDArray[np.float64], t_ns: NDArray[np.int64]
) -> NDArray[np.float64]:
    """Linear interpolation of node positions at times ``t_ns`` (relative time in float64)."""
    t = (t_ns - node_ns[0]).astype(np.float64)
    tn = (node_ns - node_ns[0]).astype(np.float64)
    return np.column_stack([np.interp(t, tn, node_xyz[:, k]) for k in range(3)])


def _gauss_markov(
    rng: np.random.Generator, t_s: NDArray[np.float64], sigma: float, tau_s: float
) -> NDArray[np.float64]:
    """A stationary first-order Gauss-Markov process (per axis ``sigma``) at times ``t_s``,
    two independent axes."""
    out = np.empty((len(t_s), 2))
    out[0] = rng.normal(0.0, sigma, 2)
    phi = np.exp(-np.diff(t_s) / tau_s)
    step = rng.normal(0.0, 1.0, (len(t_s) - 1, 2)) * (sigma * np.sqrt(1.0 - phi**2))[:, None]
    for k in range(1, len(t_s)):
        out[k] = phi[k - 1] * out[k - 1] + step[k - 1]
    return out


def simulate_gnss(
    rng: np.random.Generator,
    chain: FrameChain,
    node_ns: NDArray[np.int64],
    node_xyz_crs: NDArray[np.float64],
    model: GnssModel = GnssModel(),
) -> SimulatedGnss:
    """Fixes of an antenna at the base origin: canopy noise, RTK windows, dropouts, outliers.

    ``h_std`` is the horizontal RMS error (per axis ``h_std / sqrt(2)``); errors are drawn in
    a local east/north/up frame and mapped through the exact chain.
    """
    period_ns = round(1e9 / model.rate_hz)
    first = int(node_ns[0]) + period_ns - int(node_ns[0]) % period_ns
    t_ns = np.arange(first, int(node_ns[-1]), period_ns, dtype=np.int64)
    t_s = (t_ns - node_ns[0]) * 1e-9
    total_s = float(t_s[-1]) if len(t_s) else 0.0
    keep = ~_in_windows(t_s, _windows(rng, 0.0, total_s, model.dropouts, model.dropout_s))
    t_ns, t_s = t_ns[keep], t_s[keep]
    n = len(t_ns)
    true_xyz = interpolate_positions(node_ns, node_xyz_crs, t_ns)
    rtk = _in_windows(t_s, _windows(rng, 0.0, total_s, model.rtk_windows, model.rtk_window_s))
    rtk |= model.open_sky
    dgps = rng.random(n) < 0.4
    h_std = np.where(rtk, rng.uniform(*model.rtk_h_std, n), rng.uniform(*model.canopy_h_std, n))
    v_std = h_std * np.where(rtk, 1.5, 1.8)
    quality = np.where(rtk, FixQuality.RTK_FIXED, np.where(dgps, FixQuality.DGPS, FixQuality.GPS))
    err = np.column_stack(
        [
            rng.normal(0, 1, n) * h_std / np.sqrt(2),
            rng.normal(0, 1, n) * h_std / np.sqrt(2),
            rng.normal(0, 1, n) * v_std,
        ]
    )
    # correlated errors are drawn only when asked for: the default stream stays as it was
    if model.walk_h_m > 0 and n:
        err[:, :2] += _gauss_markov(rng, t_s, model.walk_h_m / np.sqrt(2), model.walk_tau_s)
    if model.bias_h_m > 0:
        err[:, :2] += rng.normal(0.0, model.bias_h_m / np.sqrt(2), 2)
    if model.float_share > 0:
        floating = ~rtk & (rng.random(n) < model.float_share)
        quality = np.where(floating, FixQuality.RTK_FLOAT, quality)
    if model.stated_h_m is not None:
        h_std = np.where(rtk, h_std, model.stated_h_m)
        v_std = h_std * np.where(rtk, 1.5, 1.8)
    outlier = (~rtk | model.open_sky) & (rng.random(n) < model.outlier_fraction)
    k = int(outlier.sum())
    bearing = rng.uniform(0, 2 * np.pi, k)
    dist = rng.uniform(*model.outlier_m, k)
    err[outlier] += np.column_stack(
        [dist * np.cos(bearing), dist * np.sin(bearing), rng.normal(0, 5.0, k)]
    )
    true_enu = chain.lla_to_enu(chain.crs_to_lla(true_xyz))
    lla = chain.enu_to_lla(true_enu + err)
    fixes = GnssFixes(
        stamps_ns=t_ns,
        lat=lla[:, 0],
        lon=lla[:, 1],
        alt=lla[:, 2],
        quality=quality.astype(np.int8),
        h_std=np.round(h_std, 3).astype(np.float64),
        v_std=np.round(v_std, 3).astype(np.float64),
    )
    return SimulatedGnss(fixes, true_xyz, outlier)


def simulate_imu(
    rng: np.random.Generator,
    node_ns: NDArray[np.int64],
    poses: Matrix4,
    t0_ns: int,
    t1_ns: int,
    rate_hz: float = 10.0,
) -> ImuSamples:
    """Specific force (gravity seen in the base frame) and yaw rate, plus white noise.

    A sample at ``t`` in the node interval ``[node_ns[k], node_ns[k + 1])`` sees the
    orientation of node ``k`` and the yaw rate of that interval.
    """
    period_ns = round(1e9 / rate_hz)
    t_ns = np.arange(t0_ns, t1_ns + 1, period_ns, dtype=np.int64)
    n = len(node_ns)
    k = np.clip(np.searchsorted(node_ns, t_ns, side="right") - 1, 0, max(n - 2, 0))
    rot = poses[k, :3, :3]
    accel = np.einsum("nji,j->ni", rot, np.array([0.0, 0.0, GRAVITY]))
    yaw = Rotation.from_matrix(poses[:, :3, :3]).as_euler("ZYX")[:, 0]
    dt = np.diff(node_ns).astype(np.float64) * 1e-9
    rate = np.concatenate([np.angle(np.exp(1j * np.diff(yaw))) / dt, [0.0]])
    gyro = np.column_stack([np.zeros(len(t_ns)), np.zeros(len(t_ns)), rate[k]])
    accel = accel + rng.normal(0.0, 0.02, accel.shape)
    gyro = gyro + rng.normal(0.0, 0.002, gyro.shape)
    return ImuSamples(t_ns, np.round(accel, 5), np.round(gyro, 6))
