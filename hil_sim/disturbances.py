"""Load forces on the cylinders: static loads, load steps and band-limited random forces.

A disturbance is precomputed as a table of load forces, one row per control period
(the plant holds the force over the period), so a run is reproducible from its seed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import butter, lfilter

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LoadStep:
    """From ``t_s`` on, cylinder ``cylinder`` (0-based) carries ``delta_n`` more."""

    t_s: float
    cylinder: int
    delta_n: float


def band_limited_noise(
    n_samples: int, dt_s: float, rms: float, bandwidth_hz: float, rng: np.random.Generator
) -> FloatArray:
    """Gaussian white noise through a 2nd-order Butterworth low-pass, scaled to ``rms``.

    The filter starts at rest, so the noise grows in smoothly from its first sample;
    the scaling makes the sample RMS of the returned sequence exactly ``rms``.
    """
    if n_samples <= 0 or rms == 0:
        return np.zeros(max(n_samples, 0))
    nyquist = 0.5 / dt_s
    if not 0 < bandwidth_hz < nyquist:
        raise ValueError(f"bandwidth_hz must be within (0, {nyquist}) Hz, got {bandwidth_hz}")
    b, a = butter(2, bandwidth_hz / nyquist)
    noise = np.asarray(lfilter(b, a, rng.standard_normal(n_samples)), dtype=np.float64)
    return noise * (rms / float(np.sqrt(np.mean(noise**2))))


def load_profile(
    n_samples: int,
    dt_s: float,
    static_n: Sequence[float],
    steps: Sequence[LoadStep] = (),
    noise_rms_n: float = 0.0,
    noise_bandwidth_hz: float = 1.0,
    noise_start_s: float = 0.0,
    seed: int = 0,
) -> FloatArray:
    """Load force on each cylinder at each control period, shape (n_samples, N), newtons.

    Sample ``k`` is the force over ``[k dt, (k+1) dt)``. The random forces of the
    cylinders are independent (one generator, one column each), zero before
    ``noise_start_s`` and of RMS ``noise_rms_n`` after it.
    """
    n = len(static_n)
    loads = np.tile(np.asarray(static_n, dtype=np.float64), (n_samples, 1))
    t = np.arange(n_samples) * dt_s
    for step in steps:
        if not 0 <= step.cylinder < n:
            raise ValueError(f"load step on cylinder {step.cylinder}: only {n} cylinders")
        loads[t >= step.t_s - 1e-12, step.cylinder] += step.delta_n
    if noise_rms_n > 0:
        first = int(np.searchsorted(t, noise_start_s - 1e-12))
        rng = np.random.default_rng(seed)
        for i in range(n):
            loads[first:, i] += band_limited_noise(
                n_samples - first, dt_s, noise_rms_n, noise_bandwidth_hz, rng
            )
    return loads
