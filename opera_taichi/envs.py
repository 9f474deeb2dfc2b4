"""Gymnasium environments on the Python API.

`ZX120DigEnv` ("opera_taichi/ZX120Dig-v0"): the ZX120 of scenes/zx120_excavation.yaml over its dirt bed, driven by
an agent through joint velocity targets instead of the scene's motion script.

    import gymnasium, opera_taichi
    env = gymnasium.make("opera_taichi/ZX120Dig-v0")   # coarse soil by default (DEFAULT_OVERRIDES)
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

The first reset builds the Simulation (Taichi, PyBullet, the settled bed from the disk cache) and keeps a copy of
its initial State; every later reset puts that copy back with `sim.set_state`, so an episode starts from the same
settled soil, bit for bit, without settling it again.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from . import paths
from .control import Control, MachineControl
from .errors import DivergenceError

#: Default soil: grains of 12 cm radius, about 1k particles (the scene's own 8 cm radius gives about 3.5k), for fast
#: episodes. Pass overrides={} for the scene as it is.
DEFAULT_OVERRIDES = {"soil.overrides.radius": 0.12}

#: Default price of the actuators' work in the reward: kg of soil per joule. 1e-4 makes 10 kJ of joint work
#: (lifting a 1 t load by 1 m) cost as much as 1 kg of soil gained in the bucket.
DEFAULT_ENERGY_COEF = 1e-4

FORCE_BOUND = 1.0e6    # N, |soil force on the bucket| in the observation (clipped there)
TORQUE_BOUND = 1.0e6   # N m
NOISE_MARGIN = 1.0     # rad: a reset's init_noise may exceed the environment's by this (the observation bound)
REACH_BOUND = 20.0     # m, |tip position - machine base| per axis in the observation


def dig_reward(env: "ZX120DigEnv", prev_obs: dict, obs: dict, action: np.ndarray) -> float:
    """Default reward: soil mass gained in the bucket over the step (kg) minus `env.energy_coef` (kg/J) times the
    actuators' work over the step, sum over joints and rigid steps of |effort * qd| * dt (J)."""
    gained = float(obs["bucket_mass"][0]) - float(prev_obs["bucket_mass"][0])
    return gained - env.energy_coef * env.last_energy


class ZX120DigEnv(gym.Env):
    """Dig with the ZX120: joint velocity targets in, joints, bucket wrench, terrain and bucket load out.

    Action: Box of joint velocity targets (rad/s), one per actuated joint (`joint_names`: swing, boom, arm, bucket),
    bounded by the actuators' speed limits; applied as `MachineControl(qd_target=...)` on every rigid step of the
    control period (a zero action holds the machine where it is; a joint stops at its limits).

    Observation (a Dict, all float32, values clipped into the space's bounds):
      q             (n_joints,) joint positions, rad (bounds: the joint limits; a joint without limits, the swing,
                    the range its speed limit reaches in an episode)
      qd            (n_joints,) joint velocities, rad/s (bounds: twice the speed limits)
      tip           (3,) cutting edge (the machine's tip link origin), world frame, m
      bucket_wrench (6,) soil on the bucket over the last rigid step: force N, torque N m about the bucket link
                    origin, world frame (bounds +-1e6)
      heightmap     (patch_cells, patch_cells) terrain height, m, relative to the ground plane z = 0, on a square
                    patch of world-axis-aligned cells of `patch_cell` m centred on the cutting edge's (x, y) (bounds:
                    the soil domain's z range)
      bucket_mass   (1,) soil mass inside the bucket's convex hull (its struck volume), kg

    Reward: `reward_fn(env, prev_obs, obs, action) -> float`; default `dig_reward` (see there). `info` carries
    `t` (s), `energy` (J, the actuators' work over the step; also `env.last_energy`) and `soil_mass` (kg).
    Terminated: the simulation diverged (`info["diverged"]` names why; reset to go on). Truncated: the episode
    reached `max_episode_seconds` of simulated time.
    """

    metadata = {"render_modes": []}

    def __init__(self, scene: str | Path | None = None, overrides: dict | None = None, control_period: float = 0.05,
                 max_episode_seconds: float = 20.0, reward_fn: Callable | None = None,
                 energy_coef: float = DEFAULT_ENERGY_COEF, init_noise: float = 0.0, patch_cells: int = 16,
                 patch_cell: float = 0.1, machine: str | None = None, arch: str = "cpu", render_mode=None):
        from .model import build_model
        from .scene import load_scene

        if render_mode is not None:
            raise ValueError(f"render_mode: this environment renders nothing (render_modes "
                             f"{self.metadata['render_modes']}), got {render_mode!r}")
        self.render_mode = None
        self.scene_path = Path(scene) if scene is not None else paths.scenes_dir() / "zx120_excavation.yaml"
        self.overrides = dict(DEFAULT_OVERRIDES if overrides is None else overrides)
        self.overrides["motion"] = None  # the agent is the controller
        self.scene = load_scene(self.scene_path, [f"{k}={_yaml_value(v)}" for k, v in self.overrides.items()])
        self.model = build_model(self.scene)
        if self.model.soil is None:
            raise ValueError(f"{self.scene_path}: the scene has no soil to dig")
        try:
            mm = self.model.machine(machine)
        except KeyError as exc:
            raise ValueError(f"machine: {exc.args[0]}") from None
        self.machine_name = mm.name
        self.joint_names = list(mm.joints)
        self.dt = float(self.model.dt)
        for name, value, least in (("control_period", control_period, -math.inf),
                                   ("max_episode_seconds", max_episode_seconds, -math.inf),
                                   ("init_noise", init_noise, 0.0), ("energy_coef", energy_coef, 0.0)):
            if not (isinstance(value, (int, float, np.number)) and math.isfinite(value) and value >= least):
                raise ValueError(f"{name}: expected a finite number{' >= 0' if least == 0.0 else ''}, got {value!r}")
        if reward_fn is not None and not callable(reward_fn):
            raise ValueError(f"reward_fn: expected a function reward_fn(env, prev_obs, obs, action), got {reward_fn!r}")
        self.n_sub = int(round(float(control_period) / self.dt))
        if self.n_sub < 1 or not math.isclose(self.n_sub * self.dt, float(control_period), rel_tol=1e-6):
            raise ValueError(f"control_period: {control_period} s is not a whole number (>= 1) of rigid steps of "
                             f"{self.dt} s")
        self.control_period = self.n_sub * self.dt
        self.max_episode_seconds = float(max_episode_seconds)
        if not self.max_episode_seconds >= self.control_period:
            raise ValueError(f"max_episode_seconds: expected at least one control period ({self.control_period} s), "
                             f"got {max_episode_seconds}")
        self.max_steps = int(math.ceil(self.max_episode_seconds / self.control_period - 1e-9))
        self.reward_fn = reward_fn or dig_reward
        self.energy_coef = float(energy_coef)
        self.init_noise = float(init_noise)
        self.patch_cells, self.patch_cell = int(patch_cells), float(patch_cell)
        if self.patch_cells < 1 or self.patch_cells != patch_cells or not self.patch_cell > 0:
            raise ValueError(f"patch_cells, patch_cell: expected a whole number >= 1 of cells of a positive size (m), "
                             f"got {patch_cells}, {patch_cell}")
        self.arch = arch
        self._tool = next(i for i, b in enumerate(self.model.bindings)
                          if b.owner == mm.name and b.link in mm.description.soil_links)

        desc = mm.description
        max_speed = np.array([desc.actuators[j].max_speed for j in self.joint_names], dtype=np.float64)
        q0 = np.array([mm.initial_q[j] for j in self.joint_names])
        lower = np.array([desc.joint_limits.get(j, (-math.inf, math.inf))[0] for j in self.joint_names])
        upper = np.array([desc.joint_limits.get(j, (-math.inf, math.inf))[1] for j in self.joint_names])
        reach = np.abs(q0) + self.init_noise + NOISE_MARGIN + max_speed * self.max_episode_seconds
        self._q_low = np.where(np.isfinite(lower), lower, -reach).astype(np.float32)
        self._q_high = np.where(np.isfinite(upper), upper, reach).astype(np.float32)
        self._lower, self._upper = lower, upper
        self.max_speed = max_speed
        n = len(self.joint_names)
        base = np.asarray(mm.base_xyz, dtype=np.float32)
        z_lo, z_hi = float(self.model.soil.domain_min[2]), float(self.model.soil.domain_max[2])
        hull = self.model.bindings[self._tool].mesh.convex_hull
        grain_density = getattr(self.model.soil.params, "solid_density", None) or 2.0 * self.model.soil.bulk.density
        f32 = np.float32
        self.observation_space = spaces.Dict({
            "q": spaces.Box(self._q_low, self._q_high, (n,), f32),
            "qd": spaces.Box(-2.0 * max_speed.astype(f32), 2.0 * max_speed.astype(f32), (n,), f32),
            "tip": spaces.Box(base - REACH_BOUND, base + REACH_BOUND, (3,), f32),
            "bucket_wrench": spaces.Box(np.array([-FORCE_BOUND] * 3 + [-TORQUE_BOUND] * 3, f32),
                                        np.array([FORCE_BOUND] * 3 + [TORQUE_BOUND] * 3, f32), (6,), f32),
            "heightmap": spaces.Box(f32(z_lo), f32(z_hi), (self.patch_cells, self.patch_cells), f32),
            "bucket_mass": spaces.Box(f32(0.0), f32(2.0 * hull.volume * grain_density), (1,), f32),
        })
        self.action_space = spaces.Box(-max_speed.astype(f32), max_speed.astype(f32), (n,), f32)
        self._offsets = (np.arange(self.patch_cells) - 0.5 * (self.patch_cells - 1)) * self.patch_cell

        self.sim = None
        self._initial = None        # State of the settled start (with the soil arrays)
        self._obs = None
        self._steps = 0
        self._diverged: str | None = None
        self.last_energy = 0.0

    # ------------------------------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        unknown = set(options or {}) - {"init_noise"}
        if unknown:
            raise ValueError(f"reset options: unknown {sorted(unknown)} (known: init_noise)")
        noise = (options or {}).get("init_noise", self.init_noise)
        # (an unlimited joint's observation bound was sized for the constructor's noise and a margin: a larger one
        # could start it beyond the bound, where the observation would be clipped)
        if not (isinstance(noise, (int, float, np.number)) and 0.0 <= noise <= self.init_noise + NOISE_MARGIN):
            raise ValueError(f"reset options: init_noise: expected a number from 0 to {self.init_noise + NOISE_MARGIN:g} "
                             f"rad (the environment's init_noise + {NOISE_MARGIN:g}; make it with a larger one), got "
                             f"{noise!r}")
        noise = float(noise)
        if self.sim is None:
            self._build()
        state = self._initial
        if noise > 0.0:
            state = state.copy()
            ms = state.machines[self.machine_name]
            q = ms.q + self.np_random.uniform(-noise, noise, size=ms.q.shape)
            ms.q = np.clip(q, self._lower, self._upper)
            ms.q_target = ms.q.copy()
        self.sim.set_state(state)
        self._steps, self._diverged, self.last_energy = 0, None, 0.0
        self._obs = self._observe()
        return _copy_obs(self._obs), self._info()

    def step(self, action):
        if self.sim is None:
            raise RuntimeError("call reset() before step()")
        if self._diverged is not None:
            raise RuntimeError(f"the simulation diverged ({self._diverged}); call reset()")
        if self._steps >= self.max_steps:
            raise RuntimeError(f"the episode was truncated at max_episode_seconds = {self.max_episode_seconds:g} s; "
                               f"call reset()")
        try:
            action = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"action: expected {len(self.joint_names)} finite joint velocities (rad/s), got "
                             f"{action!r:.80}") from None
        if action.shape != (len(self.joint_names),) or not np.all(np.isfinite(action)):
            raise ValueError(f"action: expected {len(self.joint_names)} finite joint velocities (rad/s), got {action}")
        action = np.clip(action, -self.max_speed, self.max_speed)
        control = Control({self.machine_name: MachineControl(qd_target=dict(zip(self.joint_names, action.tolist())))},
                          source="gymnasium")
        machine = self.sim.machines[self.machine_name]
        energy = 0.0
        prev = self._obs
        try:
            for _ in range(self.n_sub):
                control.t = self.sim.t_next
                self.sim.step(control)
                _, qd, effort = machine.joint_states()
                energy += float(np.sum(np.abs(effort * qd))) * self.dt
            obs = self._observe()
        except DivergenceError as exc:
            self._diverged = str(exc)
            self.last_energy = energy
            info = self._info()
            info["diverged"] = self._diverged
            return _copy_obs(prev), 0.0, True, False, info
        self.last_energy = energy
        self._steps += 1
        self._obs = obs
        reward = float(self.reward_fn(self, prev, obs, action))
        truncated = self._steps >= self.max_steps
        return _copy_obs(obs), reward, False, truncated, self._info()

    def close(self):
        if self.sim is not None:
            self.sim.close()
            self.sim = None
            self._initial = None

    # ------------------------------------------------------------------------------------------ internals
    def _build(self) -> None:
        from .simulation import Simulation

        sim = Simulation(self.model, arch=self.arch, quiet=True)
        sim.scene = self.scene
        self.sim = sim
        self._initial = sim.get_state()

    def _observe(self) -> dict:
        sim = self.sim
        machine = sim.machines[self.machine_name]
        q, qd, _ = machine.joint_states()
        tip = machine.link_state(machine.desc.tip_link)[0]
        hm = sim.soil.heightmap(tip[0] + self._offsets, tip[1] + self._offsets)
        mass = sim.soil_in_tools()[self.model.bindings[self._tool].name]
        raw = {"q": q, "qd": qd, "tip": tip, "bucket_wrench": sim.tool_wrench[self._tool], "heightmap": hm,
               "bucket_mass": np.array([mass])}
        for key, value in raw.items():
            if not np.all(np.isfinite(value)):
                raise DivergenceError(f"observation {key} is not finite at t = {sim.t:.4f} s")
        out = {}
        for key, space in self.observation_space.spaces.items():
            out[key] = np.clip(np.asarray(raw[key], dtype=np.float64).reshape(space.shape), space.low,
                               space.high).astype(np.float32)
        return out

    def _info(self) -> dict:
        budget = self.sim.soil.mass_budget()
        return {"t": float(self.sim.t), "energy": float(self.last_energy), "soil_mass": float(sum(budget.values()))}


def _copy_obs(obs: dict) -> dict:
    return {k: v.copy() for k, v in obs.items()}


def _yaml_value(value) -> str:
    """A `--set` value: JSON is YAML (null, numbers, lists, quoted strings)."""
    import json

    return json.dumps(value)
