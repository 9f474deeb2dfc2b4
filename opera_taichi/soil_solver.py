"""The soil solver protocol and its registry, keyed by the scene's `soil.model`.

The simulation talks to a soil only through this interface: tools in (meshes, then a pose and twist per step),
the wrench on each tool out, and the outputs the observers read. A new solver (MPM) registers here and changes
nothing in the loop; tests/test_soil_contract.py runs the same contract over every registered solver.
"""
from __future__ import annotations

from typing import ClassVar, Protocol, runtime_checkable

import numpy as np

from .errors import UserError


@runtime_checkable
class SoilSolver(Protocol):
    name: ClassVar[str]
    version: ClassVar[int]
    dt: float                     # s, the solver's own substep

    @classmethod
    def map_parameters(cls, soil_cfg):
        """(bulk, params): the user's bulk soil and the solver's parameters for it (bulk-to-micro mapping)."""

    @classmethod
    def from_model(cls, soil, *, build_beds: bool = True) -> "SoilSolver":
        """The solver for a Model's SoilModel, its beds built (cached) unless build_beds is False."""

    def add_tool(self, name: str, mesh) -> int:
        """A rigid tool by its mesh in the link frame; returns its index."""

    def set_tool_state(self, i: int, position, quat_xyzw, lin_vel, ang_vel) -> None:
        """Pose and twist of tool i's link origin, world frame, at the start of the next advance."""

    def advance(self, duration: float) -> np.ndarray:
        """Advance by `duration` s; (n_tools, 6) mean force and torque (about each link origin) on each tool."""

    def heightmap(self, x_axis: np.ndarray, y_axis: np.ndarray) -> np.ndarray:
        """Terrain height (m) at the nodes of the two axes, z[ix, iy]."""

    def mass_budget(self) -> dict[str, float]:
        """kg: {'particles': in the solver, 'out_of_domain': booked as lost since it was built, ...}."""

    def particles(self, fields=None) -> dict[str, np.ndarray]:
        """positions, velocities, radii, masses of the soil's particles (copies); only those named in `fields`."""

    def set_particles(self, positions, velocities=None, radii=None, angular_velocities=None) -> None:
        """Replace the soil by these particles (tests, scans)."""

    def get_state(self) -> dict[str, np.ndarray]:
        """Everything that changes, as arrays: set_state of it continues bit for bit."""

    def set_state(self, state: dict[str, np.ndarray]) -> None: ...

    def describe(self) -> dict:
        """The manifest's soil block."""

    @property
    def n_particles(self) -> int: ...


SOIL_SOLVERS: dict[str, type] = {}


def register_soil_solver(cls: type) -> type:
    """Register a solver class under its `name` (usable as a decorator)."""
    SOIL_SOLVERS[cls.name] = cls
    return cls


def _builtin() -> None:
    if "dem" not in SOIL_SOLVERS:
        from .dem_soil import DemSoil

        register_soil_solver(DemSoil)


def solver_class(name: str) -> type:
    _builtin()
    try:
        return SOIL_SOLVERS[name]
    except KeyError:
        raise UserError(f"soil.model: no soil solver {name!r} (registered: {', '.join(sorted(SOIL_SOLVERS))})") \
            from None
