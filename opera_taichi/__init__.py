"""opera-taichi: a Taichi soil solver coupled two-way to a PyBullet excavator."""
import importlib.util as _ilu
import os as _os
import sys as _sys
from pathlib import Path as _Path

__version__ = "0.1.0"

# Taichi prints a version banner on import; the run folder records versions, so keep stdout clean.
_os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")

# An installed copy has opera_taichi.kernels (setuptools package-dir). A source checkout keeps
# kernels/ beside this package; register it under the same name so `python cli.py` works uninstalled.
_checkout_kernels = _Path(__file__).resolve().parent.parent / "kernels" / "__init__.py"
if "opera_taichi.kernels" not in _sys.modules and _checkout_kernels.is_file() \
        and not (_Path(__file__).resolve().parent / "kernels").exists():
    _spec = _ilu.spec_from_file_location("opera_taichi.kernels", _checkout_kernels,
                                         submodule_search_locations=[str(_checkout_kernels.parent)])
    _mod = _ilu.module_from_spec(_spec)
    _sys.modules["opera_taichi.kernels"] = _mod
    _spec.loader.exec_module(_mod)

# The Python API, imported on first use (Taichi and PyBullet load only when a simulation is made).
_LAZY = {"Simulation": "simulation", "Model": "model", "build_model": "model", "State": "state",
         "MachineState": "state", "Control": "control", "MachineControl": "control", "Observer": "observers",
         "ThreadedObserver": "observers", "run_scene": "runner", "load_scene": "scene",
         "ScriptController": "control", "CallableController": "control", "SOIL_SOLVERS": "soil_solver",
         "register_soil_solver": "soil_solver", "ZX120DigEnv": "envs"}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _register_gymnasium_envs():
    """`gymnasium.make("opera_taichi/ZX120Dig-v0")` after `import opera_taichi`, where gymnasium is installed
    (registering is cheap; opera_taichi.envs, Taichi and PyBullet load only when the environment is made)."""
    try:
        import gymnasium
    except ImportError:  # gymnasium is optional at import time; the simulator works without it
        return

    if "opera_taichi/ZX120Dig-v0" not in gymnasium.registry:
        gymnasium.register(id="opera_taichi/ZX120Dig-v0", entry_point="opera_taichi.envs:ZX120DigEnv")


_register_gymnasium_envs()
