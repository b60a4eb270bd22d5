"""Synchronization of a group of cylinders by dual-error feedback (model.md section 10).

Each cylinder's controller is driven by its tracking error plus lambda times its
synchronization error, ``E_i = e_i + lambda eps_i`` with ``e_i = r_i - y_i``. The
synchronization error compares tracking errors, so cylinders with different
references (a linked layer, where ``d_3 = -d_1``) are synchronized too:

- ``"mean_deviation"``: ``eps_i = e_i - mean(e)`` (the deviation from the group);
- ``"cross_coupled"``: ``eps_i = sum over neighbours j of (e_i - e_j)``, the
  neighbours of cylinder i being i-1 and i+1 around the ring (a layer's platform
  edges 1-2-3-4-1; for two cylinders, each other).

For two cylinders ``eps_1 = (e_1 - e_2) / 2`` (mean deviation) or ``e_1 - e_2``
(cross coupled). A cylinder that lags its group has ``eps_i > 0`` and is pushed on.
The group applies ``E_i`` by handing each controller the shifted reference
``r_i + lambda eps_i``, so any controller with ``update(reference, measurement)``
(LADRC, PID) can be coupled.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

SyncScheme = Literal["mean_deviation", "cross_coupled"]


class Controller(Protocol):
    """What a group member offers (LADRC and PID do)."""

    def update(
        self, reference: float, measurement: float, reference_rate: float = 0.0
    ) -> float: ...

    def reset(self, measurement: float, command: float = 0.0) -> None: ...

    @property
    def holding_command(self) -> float: ...


def ring_neighbours(n: int) -> list[tuple[int, ...]]:
    """Neighbours of each of ``n`` cylinders around the ring (``n`` >= 2)."""
    if n < 2:
        raise ValueError(f"a synchronization group needs at least 2 cylinders, got {n}")
    return [tuple(sorted({(i - 1) % n, (i + 1) % n})) for i in range(n)]


def sync_errors(
    tracking_errors: Sequence[float], scheme: SyncScheme = "mean_deviation"
) -> list[float]:
    """Synchronization error of each cylinder from the group's tracking errors."""
    e = [float(v) for v in tracking_errors]
    n = len(e)
    if scheme == "mean_deviation":
        if n < 2:
            raise ValueError(f"a synchronization group needs at least 2 cylinders, got {n}")
        mean = sum(e) / n
        return [v - mean for v in e]
    if scheme == "cross_coupled":
        return [sum(e[i] - e[j] for j in nb) for i, nb in enumerate(ring_neighbours(n))]
    raise ValueError(f"scheme must be 'mean_deviation' or 'cross_coupled', got {scheme!r}")


class SyncGroup:
    """A linked group of cylinders, each with its own controller, coupled by dual error."""

    def __init__(
        self,
        controllers: Sequence[Controller],
        scheme: SyncScheme = "mean_deviation",
        coupling_lambda: float = 1.0,
    ) -> None:
        if len(controllers) < 2:
            raise ValueError("a synchronization group needs at least 2 controllers")
        if coupling_lambda < 0:
            raise ValueError(f"coupling_lambda must be >= 0, got {coupling_lambda}")
        sync_errors([0.0] * len(controllers), scheme)  # validates the scheme
        self.controllers = list(controllers)
        self.scheme: SyncScheme = scheme
        self.coupling_lambda = float(coupling_lambda)
        self.last_sync_error: list[float] = [0.0] * len(controllers)

    @property
    def n(self) -> int:
        return len(self.controllers)

    def reset(
        self,
        measurements: Sequence[float] | NDArray[np.float64],
        commands: Sequence[float] | NDArray[np.float64] | None = None,
    ) -> None:
        """Bumpless start of every member at its measurement, holding ``commands``."""
        held = [0.0] * self.n if commands is None else [float(c) for c in commands]
        for ctrl, y, u in zip(self.controllers, measurements, held, strict=True):
            ctrl.reset(float(y), u)

    def update(
        self,
        references: Sequence[float],
        measurements: Sequence[float] | NDArray[np.float64],
        reference_rates: Sequence[float] | None = None,
    ) -> NDArray[np.float64]:
        """Commands for the group from each cylinder's reference and measurement.

        ``reference_rates``: each reference's rate, handed to the controllers as
        feed-forward (None: none). The synchronization term is feedback only.
        """
        return np.array(self.commands(references, measurements, reference_rates))

    def commands(
        self,
        references: Sequence[float],
        measurements: Sequence[float] | NDArray[np.float64],
        reference_rates: Sequence[float] | None = None,
    ) -> list[float]:
        """:meth:`update` as a plain list (the attitude loop's form: no array per call)."""
        if isinstance(measurements, np.ndarray):
            ys = measurements.tolist()
        else:
            ys = [float(y) for y in measurements]
        if len(references) != len(ys) or len(ys) != len(self.controllers):
            raise ValueError(
                f"expected {len(self.controllers)} references and measurements, "
                f"got {len(references)} and {len(ys)}"
            )
        errors = [r - y for r, y in zip(references, ys, strict=True)]
        eps = sync_errors(errors, self.scheme)
        self.last_sync_error = eps
        lam = self.coupling_lambda
        ctrls = self.controllers
        if reference_rates is None:
            return [ctrls[i].update(references[i] + lam * eps[i], ys[i]) for i in range(len(ys))]
        if len(reference_rates) != len(ys):
            raise ValueError(f"expected {len(ys)} reference rates, got {len(reference_rates)}")
        return [
            ctrls[i].update(references[i] + lam * eps[i], ys[i], reference_rates[i])
            for i in range(len(ys))
        ]
