"""Station layouts and target grids for planning (:class:`Stations`, :class:`GridSpec`).

Positions are ENU, m; σ in rad (NaN elevation σ = a 1D, azimuth-only station). The grid is
laid out like nav_msgs/OccupancyGrid. Re-exported from :mod:`.planning`.
"""

from dataclasses import dataclass

import numpy as np


@dataclass
class Stations:
    """A station layout for planning: N stations, each 1D (azimuth) or 2D (azimuth+elevation).

    Attributes:
        positions: (N, 3) ENU positions, m.
        sigma_az: (N,) azimuth σ_θ, rad (> 0).
        sigma_el: (N,) elevation σ_ψ, rad (> 0), NaN for a 1D station.
        names: N station names.
    """

    # Dataclass fields: alike other field lists in shape only, there is no logic to share.
    positions: np.ndarray
    sigma_az: np.ndarray
    sigma_el: np.ndarray
    names: list = None

    @property
    def N(self):
        """Number of stations."""
        return self.positions.shape[0]

    @property
    def has_elevation(self):
        """(N,) bool: True for 2D stations."""
        return np.isfinite(self.sigma_el)

    @classmethod
    def from_arrays(cls, positions, sigma_az, sigma_el=None, has_elevation=True, names=None):
        """Build and validate a layout; raise ValueError naming the bad field.

        ``sigma_az``/``sigma_el`` (rad) are scalars or (N,) arrays; ``sigma_el`` None means
        σ_ψ = σ_θ; ``has_elevation`` a bool or (N,) mask (False = 1D station).
        """
        pos = np.asarray(positions, dtype=float)
        if pos.ndim == 1 and pos.size == 3:
            pos = pos[None]
        if pos.ndim != 2 or pos.shape[1] != 3 or pos.shape[0] == 0:
            raise ValueError(f'stations: expected positions of shape (N, 3), got {pos.shape}')
        if not np.all(np.isfinite(pos)):
            raise ValueError('stations: non-finite station coordinate')
        N = pos.shape[0]
        try:
            saz = np.broadcast_to(np.asarray(sigma_az, dtype=float), (N,)).copy()
            sel = np.broadcast_to(np.asarray(saz if sigma_el is None else sigma_el,
                                             dtype=float), (N,)).copy()
            mask = np.broadcast_to(np.asarray(has_elevation, dtype=bool), (N,))
        except ValueError:
            raise ValueError(f'sigma: expected a scalar or {N} values (one per station)') \
                from None
        if not np.all(np.isfinite(saz)) or np.any(saz <= 0):
            raise ValueError('sigma_az: must be finite and > 0')
        mask = mask & np.isfinite(sel)
        if np.any(sel[mask] <= 0):
            raise ValueError('sigma_el: must be finite and > 0 for 2D stations')
        sel = np.where(mask, sel, np.nan)
        if names is None:
            names = [f'station_{i + 1}' for i in range(N)]
        if len(names) != N:
            raise ValueError(f'names: expected {N} names, got {len(names)}')
        return cls(pos, saz, sel, list(names))

    @classmethod
    def from_scenario(cls, scenario, t=0.0, sigma_az=None, sigma_el=None):
        """Layout of a simulator scenario (core.simulation.Scenario / load_scenario).

        Station positions at scenario time ``t`` (s), 1D where ``dims`` is 1, σ from the
        scenario unless ``sigma_az``/``sigma_el`` (rad) override them for every station.
        """
        from .simulation import station_position
        st = scenario.stations
        pos = np.array([station_position(s, t) for s in st], dtype=float).reshape(-1, 3)
        saz = np.array([s.sigma_az for s in st], dtype=float)
        sel = np.array([s.sigma_el for s in st], dtype=float)
        if sigma_az is not None:
            saz = np.full(len(st), float(sigma_az))
            sel = np.full(len(st), float(sigma_az))
        if sigma_el is not None:
            sel = np.full(len(st), float(sigma_el))
        return cls.from_arrays(pos, saz, sel, [s.dims == 2 for s in st], [s.id for s in st])

    def with_station(self, position, sigma_az, sigma_el=None, has_elevation=True,
                     name='new'):
        """A new layout with one more station appended (see :meth:`from_arrays`)."""
        sel = sigma_az if sigma_el is None else sigma_el
        return Stations.from_arrays(
            np.vstack([self.positions, np.asarray(position, dtype=float)[None]]),
            np.append(self.sigma_az, sigma_az),
            np.append(self.sigma_el, sel if has_elevation else np.nan),
            np.append(self.has_elevation, bool(has_elevation)),
            list(self.names) + [name])


@dataclass
class GridSpec:
    """A horizontal grid of targets at one altitude, laid out like nav_msgs/OccupancyGrid.

    Cell (c, r) (column c along +x, row r along +y) has its centre at
    (origin_x + (c + 0.5)·resolution, origin_y + (r + 0.5)·resolution, altitude); arrays are
    (height, width), row-major, row 0 at the lowest y, exactly the order of
    OccupancyGrid.data (data[r·width + c]). (origin_x, origin_y, altitude) is the
    OccupancyGrid info.origin position. Units: m.
    """

    origin_x: float
    origin_y: float
    resolution: float
    width: int
    height: int
    altitude: float

    def __post_init__(self):
        for name in ('origin_x', 'origin_y', 'resolution', 'altitude'):
            if not np.isfinite(float(getattr(self, name))):
                raise ValueError(f'grid.{name}: must be finite')
        if self.resolution <= 0:
            raise ValueError(f'grid.resolution: must be > 0 m, got {self.resolution}')
        for name in ('width', 'height'):
            v = getattr(self, name)
            if int(v) != v or v < 1:
                raise ValueError(f'grid.{name}: must be a positive integer, got {v}')
            setattr(self, name, int(v))
        if self.width * self.height > 25_000_000:
            raise ValueError('grid: more than 25 million cells')

    @classmethod
    def from_extent(cls, xmin, xmax, ymin, ymax, resolution, altitude):
        """Grid covering [xmin, xmax] × [ymin, ymax] (m) with cells of ``resolution`` m (at
        most the shorter side; ValueError otherwise)."""
        if not (np.isfinite([xmin, xmax, ymin, ymax]).all() and xmax > xmin and ymax > ymin):
            raise ValueError('extent: need finite xmin < xmax and ymin < ymax')
        if not np.isfinite(resolution) or resolution <= 0:
            raise ValueError(f'resolution: must be > 0 m, got {resolution}')
        if resolution > min(xmax - xmin, ymax - ymin):
            # (one cell larger than the extent would be centred outside it)
            raise ValueError(f'resolution: cell size {resolution:g} m exceeds the extent '
                             f'({xmax - xmin:g} m x {ymax - ymin:g} m)')
        width = max(1, int(round((xmax - xmin) / resolution)))
        height = max(1, int(round((ymax - ymin) / resolution)))
        return cls(float(xmin), float(ymin), float(resolution), width, height, float(altitude))

    @property
    def x(self):
        """(width,) cell-centre x, m."""
        return self.origin_x + (np.arange(self.width) + 0.5) * self.resolution

    @property
    def y(self):
        """(height,) cell-centre y, m."""
        return self.origin_y + (np.arange(self.height) + 0.5) * self.resolution

    @property
    def extent(self):
        """(xmin, xmax, ymin, ymax) of the cell edges, m."""
        return (self.origin_x, self.origin_x + self.width * self.resolution,
                self.origin_y, self.origin_y + self.height * self.resolution)

    def points(self):
        """(height·width, 3) cell centres in OccupancyGrid order (row-major, row = y)."""
        X, Y = np.meshgrid(self.x, self.y)
        return np.stack([X.ravel(), Y.ravel(), np.full(X.size, float(self.altitude))], axis=-1)
