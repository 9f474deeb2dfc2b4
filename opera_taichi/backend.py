"""One place that starts Taichi, so every module agrees on the backend."""
from __future__ import annotations

import contextlib
import ctypes
import sys

import numpy as np
import taichi as ti
from taichi.lang.matrix import MatrixType

from .errors import UserError

_started: str | None = None
FAST_MATH = False   # what the kernels compile with; part of what a cached settled bed is keyed by


def init_taichi(arch: str = "cpu", *, debug: bool = False, default_fp=None) -> str:
    """Start Taichi once per process on `arch` (cpu, cuda or auto). Returns the backend in use.

    Taichi runs one backend per process and a second ti.init would free every array of every simulation in it,
    so a later call on the same backend (or `auto`) returns at once, and one asking for another backend is refused.
    """
    global _started
    if arch not in ("cpu", "cuda", "auto"):
        raise UserError(f"--arch: expected cpu, cuda or auto, got {arch!r}")
    if _started is not None and not debug and default_fp is None:
        wanted = {"cpu": ("x64", "arm64"), "cuda": ("cuda",)}.get(arch)
        if wanted is None or _started in wanted:
            return _started
        raise UserError(f"--arch {arch}: Taichi already runs on {_started} in this process (one backend per "
                        f"process); use --arch {'cuda' if _started == 'cuda' else 'cpu'} or another process")
    # fast_math off: IEEE arithmetic, so a kernel's bits do not depend on how the compiler arranges it (with it on, the
    # soil's serial and threaded variants of a substep parted by an ulp in a dig on an AVX-512 host; no slower)
    kwargs = dict(offline_cache=True, debug=debug, log_level=ti.WARN, random_seed=0, fast_math=FAST_MATH)
    if default_fp is not None:
        kwargs["default_fp"] = default_fp
    # Taichi prints its "Starting on arch=..." line to stdout: a diagnostic, so to stderr (stdout stays the run's
    # own output, empty under --quiet)
    with contextlib.redirect_stdout(sys.stderr):
        _init(arch, kwargs)
    _started = str(ti.lang.impl.current_cfg().arch).split(".")[-1]
    return _started


def _init(arch: str, kwargs: dict) -> None:
    if arch == "cpu":
        ti.init(arch=ti.cpu, **kwargs)
    elif arch == "cuda":
        try:
            ti.init(arch=ti.cuda, **kwargs)
        except Exception as exc:  # Taichi raises a bare RuntimeError when no CUDA device is present
            raise UserError(f"--arch cuda: no usable CUDA device ({exc})") from None
        if ti.lang.impl.current_cfg().arch != ti.cuda:
            raise UserError("--arch cuda: no usable CUDA device on this machine (use cpu or auto)")
    else:
        ti.init(arch=ti.gpu, **kwargs)  # falls back to CPU when no GPU is found


def current_arch() -> str | None:
    return _started


def compiled_for() -> dict:
    """What a kernel's bits depend on beyond its code and inputs: the backend (the GPU's layout sums in another order
    than the CPU's; x64 and arm64 compile differently) and the arithmetic. Results cached across runs (settled
    beds) are keyed by it, so a bed settled on a GPU is not what a CPU run starts from."""
    return {"arch": _started, "fast_math": FAST_MATH}


def host_view(arr) -> np.ndarray | None:
    """A NumPy view of a Taichi ndarray's memory on the CPU backends (the kernels run in this process's memory and
    have finished when their launch returns), else None: reading a few numbers back then costs nothing, where
    to_numpy/from_numpy launch a kernel each (~0.2 ms from Python, once per rigid step)."""
    if _started not in ("x64", "arm64") or arr.dtype not in (ti.f64, ti.f32, ti.i32):
        return None
    prog = ti.lang.impl.get_runtime().prog
    if not hasattr(prog, "get_ndarray_data_ptr_as_int"):
        return None
    ctype = {ti.f64: ctypes.c_double, ti.f32: ctypes.c_float, ti.i32: ctypes.c_int32}[arr.dtype]
    shape = tuple(arr.shape) + tuple(getattr(arr, "element_shape", None) or ())  # (vectors are stored packed)
    buffer = (ctype * int(np.prod(shape))).from_address(prog.get_ndarray_data_ptr_as_int(arr.arr))
    return np.ctypeslib.as_array(buffer).reshape(shape)


def precompile(*kernels) -> int:
    """Compile ndarray kernels (or load them from Taichi's disk cache) without launching them, so that their first
    call in a run does not compile on the run's clock. Returns how many compiled: the arguments are examples built
    from the kernels' annotations (scalars and ndarrays), through Taichi 1.7's Kernel internals; a kernel they do not
    fit, or another Taichi, compiles at its first call instead."""
    prog = ti.lang.impl.get_runtime().prog
    if prog is None:  # Taichi not started: nothing to compile for
        return 0
    done = 0
    for kernel in kernels:
        try:
            primal = kernel._primal
            args = [_example_arg(a.annotation) for a in primal.arguments]
            key = primal.ensure_compiled(*args)
            prog.compile_kernel(prog.config(), prog.get_device_caps(), primal.compiled_kernels[key])
        except Exception:  # noqa: BLE001 - only a missed optimisation: the first call compiles as usual
            continue
        done += 1
    return done


def _example_arg(annotation):
    """An argument of the annotated type; a template (a field or a compile-time value) has no example."""
    if isinstance(annotation, ti.types.ndarray_type.NdarrayType):
        return ti.ndarray(annotation.dtype, (1,) * annotation.ndim)
    if isinstance(annotation, MatrixType):  # a vector or matrix passed by value
        return annotation(*([0.0] * int(np.prod(annotation.get_shape()))))
    if annotation in (ti.f32, ti.f64):
        return 0.0
    if annotation in (ti.i32, ti.i64, ti.u32, ti.u64, ti.i8, ti.i16, ti.u8, ti.u16):
        return 0
    raise TypeError(f"no example argument for {annotation!r}")


class KernelSequence:
    """Ndarray kernels run in order, their arguments bound by name at each run: one compute graph where the backend
    builds one (one launch from Python, the arguments set in C++: a direct launch costs ~90 us of Python, about as
    much as a small rebuild's kernels take), else one launch each, the same kernels in the same order.

    steps: (kernel, argument names) in order; an array one kernel writes and the next reads goes under one name.
    run(args): args maps every name to an ndarray or a Python int or float (the kernels' annotations give the
    types)."""

    def __init__(self, steps):
        self.steps = [(kernel, tuple(names)) for kernel, names in steps]
        self.graph = None
        try:
            annotations = [[a.annotation for a in kernel._primal.arguments] for kernel, _ in self.steps]
        except AttributeError:  # another Taichi: no annotations to build a graph from
            return
        symbols, types = {}, {}
        for (kernel, names), kinds in zip(self.steps, annotations):
            if len(kinds) != len(names):
                raise TypeError(f"{kernel.__name__}: {len(kinds)} arguments, {len(names)} names")
            for name, kind in zip(names, kinds):
                if types.setdefault(name, _arg_type(kind)) != _arg_type(kind):
                    raise TypeError(f"{kernel.__name__}: argument {name!r} is {_arg_type(kind)}, elsewhere "
                                    f"{types[name]}")
        try:
            builder = ti.graph.GraphBuilder()
            for (kernel, names), kinds in zip(self.steps, annotations):
                for name, kind in zip(names, kinds):
                    symbols.setdefault(name, _graph_arg(name, kind))
                builder.dispatch(kernel, *(symbols[name] for name in names))
            self.graph = builder.compile()
        except Exception:  # noqa: BLE001 - no graph on this backend: launch the kernels one by one
            self.graph = None

    def run(self, args: dict) -> None:
        if self.graph is not None:
            self.graph.run(args)
        else:
            self.launch(args)

    def launch(self, args: dict) -> None:
        """The kernels launched one by one (where no graph could be built)."""
        for kernel, names in self.steps:
            kernel(*(args[name] for name in names))


def _arg_type(annotation) -> str:
    """An argument's type as text (two equal ndarray annotations are distinct objects that compare unequal)."""
    if isinstance(annotation, ti.types.ndarray_type.NdarrayType):
        return f"ndarray({_arg_type(annotation.dtype)}, ndim={annotation.ndim})"
    if isinstance(annotation, MatrixType):
        return f"matrix({annotation.get_shape()}, {annotation.dtype})"
    return str(annotation)


def _graph_arg(name: str, annotation):
    kind = ti.graph.ArgKind
    if isinstance(annotation, ti.types.ndarray_type.NdarrayType):
        return ti.graph.Arg(kind.NDARRAY, name, dtype=annotation.dtype, ndim=annotation.ndim)
    if annotation in (ti.f32, ti.f64, ti.i32, ti.i64):
        return ti.graph.Arg(kind.SCALAR, name, annotation)
    raise TypeError(f"{name}: no compute-graph argument for {annotation!r}")
