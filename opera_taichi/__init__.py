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
