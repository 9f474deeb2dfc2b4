"""RigidWorld: the PyBullet world (DIRECT mode) that hosts any number of machines and the ground.

One client per world, so two simulations in one process never share rigid bodies. The ground plane exists once a
machine stands on tracks; it touches only track wheels, so a bucket (or a fixed-base machine) can go below z = 0
into the soil. Machines in one world collide with each other.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

from ._quiet import quiet_c_output

with quiet_c_output():  # pybullet's C code prints its build time on import; keep stdout for our output
    import pybullet as pb

SOLVER_ITERATIONS = 150     # a 12 t machine with 50 kg wheels and 0.001 kg frame links needs more than 50


class RigidWorld:
    def __init__(self, dt: float = 1e-3, gravity: float = 9.81):
        self.dt = float(dt)
        with quiet_c_output():
            self.client = pb.connect(pb.DIRECT)
        c = self.client
        pb.setGravity(0, 0, -gravity, physicsClientId=c)
        pb.setPhysicsEngineParameter(fixedTimeStep=self.dt, numSubSteps=0, numSolverIterations=SOLVER_ITERATIONS,
                                     solverResidualThreshold=1e-9, deterministicOverlappingPairs=1,
                                     physicsClientId=c)
        self.machines: list = []
        self.ground: int | None = None

    def save_state(self) -> bytes:
        """Bullet's own state of the world, its contact points and their warm-start impulses included: restored
        with the joints and bases, the world goes on bit for bit (without them a machine on its tracks drifts
        from its first step: 3 cm in 0.6 s of driving)."""
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / "world.bullet"
            pb.saveBullet(str(path), physicsClientId=self.client)
            return path.read_bytes()

    def restore_state(self, data: bytes) -> None:
        """Put back what save_state took, in a world of the same bodies (the same model)."""
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / "world.bullet"
            path.write_bytes(bytes(data))
            pb.restoreState(fileName=str(path), physicsClientId=self.client)

    def add_machine(self, desc, **kwargs):
        """A BulletMachine of description `desc` in this world (keyword arguments as BulletMachine's)."""
        from .machine import BulletMachine

        return BulletMachine(desc, world=self, dt=self.dt, **kwargs)

    def attach(self, machine) -> None:
        """Called by BulletMachine once its body is loaded."""
        self.machines.append(machine)
        if not machine.fixed_base and self.ground is None:
            plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=self.client)
            self.ground = pb.createMultiBody(0, plane, basePosition=[0, 0, 0], physicsClientId=self.client)
            pb.changeDynamics(self.ground, -1, lateralFriction=1.0, physicsClientId=self.client)
            for other in self.machines:
                self._filter_ground(other)
        elif self.ground is not None:
            self._filter_ground(machine)

    def _filter_ground(self, machine) -> None:
        """Only track wheels touch the ground (their wheels are frictionless: the tracks' grip is tracks.py's)."""
        c = self.client
        wheels = set(machine._wheels_left + machine._wheels_right)
        for link in [-1, *range(pb.getNumJoints(machine.body, physicsClientId=c))]:
            if link not in wheels:
                pb.setCollisionFilterPair(self.ground, machine.body, -1, link, 0, physicsClientId=c)

    def step(self) -> None:
        """One rigid step of every body: motors and external forces set, then Bullet, then joint states read."""
        for m in self.machines:
            m.pre_step()
        pb.stepSimulation(physicsClientId=self.client)
        for m in self.machines:
            m.post_step()

    def close(self) -> None:
        if self.client is not None and pb.isConnected(self.client):
            pb.disconnect(self.client)
        self.client = None
