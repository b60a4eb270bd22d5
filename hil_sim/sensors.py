"""Transducers of the rig: what the PLC reads, with resolution and noise, seeded.

Each transducer draws its noise from its own ``numpy.random.Generator`` in blocks,
so a run is reproducible from the seed and cheap per sample.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

_BLOCK = 4096


class Transducer:
    """A bank of ``n`` identical transducers: ``read(true) = quantize(true + noise)``.

    ``resolution`` is the quantization step (0: none), ``noise_rms`` the standard
    deviation of white Gaussian noise, both in the measured quantity's SI unit.
    """

    def __init__(self, n: int, resolution: float, noise_rms: float, seed: int) -> None:
        if resolution < 0 or noise_rms < 0:
            raise ValueError("resolution and noise_rms must be >= 0")
        self.n = n
        self.resolution = float(resolution)
        self.noise_rms = float(noise_rms)
        self._rng = np.random.default_rng(seed)
        self._inv_res = 1.0 / resolution if resolution > 0 else 0.0
        self._block: FloatArray = np.zeros((0, n))
        self._block_len = 0  # rows of _block
        self._next = 0

    def read(self, true_value: FloatArray) -> FloatArray:
        """The readings of all ``n`` transducers for the true values (N,)."""
        return self.quantize(true_value, self.next_noise())

    def next_noise(self) -> FloatArray:
        """The noise of the next sample (n,): the stream moves on by one sample whether
        or not its reading is ever taken (:meth:`quantize`), so a run stays the same."""
        self.skip()
        return self._block[self._next - 1]

    def skip(self) -> None:
        """Move the stream on by one sample without making its noise (:meth:`last_noise`
        gives it if its reading is taken after all)."""
        if self._next >= self._block_len:
            self._block = self._rng.standard_normal((_BLOCK, self.n)) * self.noise_rms
            self._block_len = _BLOCK
            self._next = 0
        self._next += 1

    def last_noise(self) -> FloatArray:
        """The noise of the sample the stream last moved on to (:meth:`skip`)."""
        return self._block[self._next - 1]

    def quantize(self, true_value: FloatArray, noise: FloatArray) -> FloatArray:
        """The readings for the true values with one sample's ``noise``
        (:meth:`next_noise`): ``quantize(true + noise)``."""
        value = true_value + noise
        if self.resolution > 0:  # np.round(value * inv_res) * resolution, in place
            value *= self._inv_res
            np.rint(value, out=value)
            value *= self.resolution
        return value


class PositionTransducer(Transducer):
    """Rod position transducer (magnetostrictive), metres."""

    def __init__(self, n: int, resolution_m: float, noise_rms_m: float, seed: int) -> None:
        super().__init__(n, resolution_m, noise_rms_m, seed)


class PressureTransducer(Transducer):
    """Chamber pressure transducer, pascal."""

    def __init__(self, n: int, resolution_pa: float, noise_rms_pa: float, seed: int) -> None:
        super().__init__(n, resolution_pa, noise_rms_pa, seed)
