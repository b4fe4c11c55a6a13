"""OFDM numerology and resource allocation (paper, section III-A).

A :class:`ResourceGrid` is the time-frequency grid of one twin step: ``K``
OFDM symbols times ``N`` subcarriers. A :class:`ResourceSet` is the
resource set R_q = N_q x K_q of one transmitter (subcarriers x symbols) and
gives the allocation mask alpha_q ``[K, N]`` of eq. 1.

Conventions (chosen so the channel equals Sionna's ``Paths.cfr``):

* Subcarrier ``n`` (0-based array index) sits at the baseband frequency
  offset ``f_n = (n - floor(N/2)) * delta_f``, i.e. exactly
  ``sionna.rt.utils.subcarrier_frequencies(N, delta_f)``:
  ``[-N/2, ..., N/2 - 1] * delta_f`` for even N and
  ``[-(N-1)/2, ..., (N-1)/2] * delta_f`` for odd N.
* Symbol ``k`` (0-based) starts at ``t_k = k * T_s`` with the symbol time
  ``T_s = (N + cp) / (N * delta_f)`` (useful part plus cyclic prefix);
  this is Sionna's ``cfr(sampling_frequency=1/T_s, num_time_steps=K)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Mapping

import numpy as np

from ._checks import positive_float, positive_int

__all__ = ["ResourceGrid", "ResourceSet", "allocation_masks"]


@dataclass(frozen=True)
class ResourceGrid:
    """OFDM resource grid of one twin step.

    Args:
        num_subcarriers: N, number of subcarriers (FFT size, all usable).
        subcarrier_spacing_hz: delta_f [Hz].
        num_symbols: K, OFDM symbols per twin step.
        cyclic_prefix_samples: Cyclic-prefix length [samples at N*delta_f].
    """

    num_subcarriers: int
    subcarrier_spacing_hz: float
    num_symbols: int
    cyclic_prefix_samples: int = 0

    def __post_init__(self) -> None:
        positive_int("num_subcarriers", self.num_subcarriers)
        positive_float("subcarrier_spacing_hz", self.subcarrier_spacing_hz)
        positive_int("num_symbols", self.num_symbols)
        cp = self.cyclic_prefix_samples
        if isinstance(cp, bool) or not isinstance(cp, (int, np.integer)) or cp < 0:
            raise ValueError("cyclic_prefix_samples must be an integer >= 0, "
                             f"got {cp!r}")

    @property
    def shape(self) -> tuple[int, int]:
        """Grid shape ``(K, N)``."""
        return (self.num_symbols, self.num_subcarriers)

    @property
    def bandwidth_hz(self) -> float:
        """Occupied bandwidth N * delta_f [Hz]."""
        return self.num_subcarriers * self.subcarrier_spacing_hz

    @property
    def sampling_frequency_hz(self) -> float:
        """Baseband sample rate N * delta_f [Hz] (the CP is counted in these samples)."""
        return self.bandwidth_hz

    @property
    def symbol_duration_s(self) -> float:
        """T_s = (N + cp) / (N * delta_f) [s], OFDM symbol incl. cyclic prefix."""
        n = self.num_subcarriers
        return (n + self.cyclic_prefix_samples) / (n * self.subcarrier_spacing_hz)

    @property
    def step_duration_s(self) -> float:
        """K * T_s [s], the air time of one twin step (rate normalisation)."""
        return self.num_symbols * self.symbol_duration_s

    @property
    def subcarrier_indices(self) -> np.ndarray:
        """Centred integer subcarrier indices ``[N]``: ``f_n / delta_f``."""
        n = self.num_subcarriers
        return np.arange(n, dtype=np.int64) - n // 2

    @property
    def subcarrier_frequencies(self) -> np.ndarray:
        """Baseband subcarrier frequency offsets ``[N]`` [Hz], centred like
        ``sionna.rt.utils.subcarrier_frequencies``."""
        return self.subcarrier_indices.astype(np.float64) * self.subcarrier_spacing_hz

    @property
    def symbol_times(self) -> np.ndarray:
        """Start time of every OFDM symbol ``[K]`` [s]: ``k * T_s``."""
        return np.arange(self.num_symbols, dtype=np.float64) * self.symbol_duration_s


def _indices(owner: str, axis: str, size: int, spec) -> np.ndarray:
    """Turn a half-open ``(start, stop)`` range, a ``range`` or an explicit
    index collection into sorted unique indices validated against ``size``."""
    if spec is None:
        return np.arange(size, dtype=np.int64)
    if isinstance(spec, range):
        spec = list(spec)
        is_range = False
    else:
        is_range = (isinstance(spec, tuple) and len(spec) == 2
                    and all(isinstance(v, (int, np.integer))
                            and not isinstance(v, bool) for v in spec))
    if is_range:
        start, stop = int(spec[0]), int(spec[1])
        if not 0 <= start < stop <= size:
            raise ValueError(
                f"transmitter {owner!r}: {axis} range [{start}, {stop}) is "
                f"outside the grid [0, {size}) or empty")
        return np.arange(start, stop, dtype=np.int64)
    arr = np.asarray(list(spec) if not isinstance(spec, np.ndarray) else spec)
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"transmitter {owner!r}: {axis} indices must be a "
                         f"non-empty 1-D collection, got shape {arr.shape}")
    if arr.dtype == bool or not np.issubdtype(arr.dtype, np.integer):
        if not (np.issubdtype(arr.dtype, np.floating)
                and np.all(np.isfinite(arr)) and np.all(arr == np.round(arr))):
            raise ValueError(f"transmitter {owner!r}: {axis} indices must be "
                             f"integers, got {arr.dtype}")
    arr = arr.astype(np.int64)
    bad = arr[(arr < 0) | (arr >= size)]
    if bad.size:
        raise ValueError(f"transmitter {owner!r}: {axis} indices {bad[:5].tolist()}"
                         f" are outside the grid [0, {size})")
    return np.unique(arr)


@dataclass(frozen=True, eq=False)
class ResourceSet:
    """Resource set R_q = N_q x K_q of one transmitter on a grid.

    Each of ``subcarriers`` and ``symbols`` is either a half-open range given
    as a 2-tuple ``(start, stop)`` (as in ``twin.toml``), a ``range``, an
    explicit collection of 0-based indices, or ``None`` for "all".
    Invalid specs raise ``ValueError`` naming the transmitter and the range.

    Attributes:
        grid: The grid the set lives on.
        name: Transmitter name (used in error messages).
        subcarrier_indices: Sorted unique subcarrier indices ``[|N_q|]``.
        symbol_indices: Sorted unique symbol indices ``[|K_q|]``.
    """

    grid: ResourceGrid
    subcarriers: object = None
    symbols: object = None
    name: str = "tx"
    subcarrier_indices: np.ndarray = field(init=False, repr=False)
    symbol_indices: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.grid, ResourceGrid):
            raise ValueError(f"transmitter {self.name!r}: grid must be a "
                             "ResourceGrid")
        sc = _indices(self.name, "subcarrier", self.grid.num_subcarriers,
                      self.subcarriers)
        sy = _indices(self.name, "symbol", self.grid.num_symbols, self.symbols)
        object.__setattr__(self, "subcarrier_indices", sc)
        object.__setattr__(self, "symbol_indices", sy)

    @property
    def num_resource_elements(self) -> int:
        """|R_q| = |N_q| * |K_q|."""
        return int(self.subcarrier_indices.size * self.symbol_indices.size)

    @property
    def mask(self) -> np.ndarray:
        """Allocation mask alpha_q ``[K, N]`` (bool): True where q transmits."""
        k, n = self.grid.shape
        m = np.zeros((k, n), dtype=bool)
        m[np.ix_(self.symbol_indices, self.subcarrier_indices)] = True
        return m

    def overlaps(self, other: "ResourceSet") -> np.ndarray:
        """Mask ``[K, N]`` of resource elements shared with ``other``."""
        if other.grid != self.grid:
            raise ValueError(f"transmitters {self.name!r} and {other.name!r} "
                             "use different grids")
        return self.mask & other.mask


def allocation_masks(resource_sets: Mapping[str, ResourceSet] | Iterable[ResourceSet]
                     ) -> np.ndarray:
    """Stack allocation masks alpha ``[Q, K, N]`` of several transmitters
    (in the given order); all sets must share one grid."""
    sets = list(resource_sets.values()) if isinstance(resource_sets, Mapping) \
        else list(resource_sets)
    if not sets:
        raise ValueError("resource_sets is empty")
    grid = sets[0].grid
    for s in sets[1:]:
        if s.grid != grid:
            raise ValueError(f"transmitter {s.name!r} uses a different grid "
                             f"than {sets[0].name!r}")
    return np.stack([s.mask for s in sets])
