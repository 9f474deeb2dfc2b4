"""backend.host_view: on the CPU a NumPy view of a Taichi ndarray's own memory (what a kernel writes is read without a
copy, what the host writes a kernel reads), the route by which every soil step's tool rows go in and its report
comes out."""
import numpy as np
import taichi as ti

from opera_taichi.backend import current_arch, host_view, init_taichi


@ti.kernel
def _double_plus_row(a: ti.types.ndarray(ti.f64, 2)):
    for i, j in ti.ndrange(a.shape[0], a.shape[1]):
        a[i, j] = 2.0 * a[i, j] + i


def test_a_host_view_shares_the_arrays_memory_both_ways():
    if current_arch() is None:
        init_taichi("cpu")
    arr = ti.ndarray(ti.f64, (4, 3))
    view = host_view(arr)
    assert view is not None and view.shape == (4, 3) and not view.flags.owndata
    view[:] = np.arange(12.0).reshape(4, 3)          # written by the host ...
    _double_plus_row(arr)                              # ... read and rewritten by a kernel ...
    expected = 2.0 * np.arange(12.0).reshape(4, 3) + np.arange(4.0)[:, None]
    assert np.array_equal(view, expected)              # ... seen through the view, no copy
    assert np.array_equal(arr.to_numpy(), expected)
    assert host_view(ti.ndarray(ti.i64, 3)) is None    # a type it does not map: the caller copies


def test_a_host_view_of_a_vector_array_has_its_element_axes():
    """Vector ndarrays (the particles' positions, velocities and spins) are stored element by element: the view
    adds the element's axis and reads what to_numpy reads (DemSoil.particles of a big soil, without copies)."""
    if current_arch() is None:
        init_taichi("cpu")
    arr = ti.ndarray(ti.types.vector(3, ti.f64), (5, 3))
    values = np.arange(45.0).reshape(5, 3, 3)
    arr.from_numpy(values)
    view = host_view(arr)
    assert view is not None and view.shape == (5, 3, 3)
    assert np.array_equal(view, values) and np.array_equal(view, arr.to_numpy())


@ti.kernel
def _scaled_sum(a: ti.types.ndarray(ti.f32, 1), scale: ti.f64) -> ti.f64:
    total = 0.0
    for i in range(a.shape[0]):
        total += scale * a[i]
    return total


@ti.kernel
def _fill_field(f: ti.template(), value: ti.f64):
    for i in f:
        f[i] = value


@ti.kernel
def _times(a: ti.types.ndarray(ti.f64, 1), k: ti.template()):
    for i in range(a.shape[0]):
        a[i] *= k


def test_precompile_compiles_without_a_launch_and_skips_what_it_cannot_fit():
    """precompile (DemSoil.warm_up's rebuild and observer kernels) materialises a kernel from its annotations alone
    (Taichi's front end: what its first call from the disk cache cost) and hands it to the backend, so its first call
    finds it built; a kernel with a template argument (a field, a compile-time value) is left to its first call.
    (Whether the backend compiled it too is not visible from Python: the kernel's first call would do it.)"""
    from opera_taichi import dem_soil
    from opera_taichi.backend import precompile
    from opera_taichi.kernels import dem
    if current_arch() is None:
        init_taichi("cpu")
    assert precompile(_scaled_sum) == 1
    compiled = dict(_scaled_sum._primal.compiled_kernels)
    arr = ti.ndarray(ti.f32, 4)
    arr.from_numpy(np.arange(4, dtype=np.float32))
    assert _scaled_sum(arr, 2.0) == 12.0
    assert _scaled_sum._primal.compiled_kernels == compiled       # the call found it compiled
    assert precompile(_fill_field) == 0 and not _fill_field._primal.compiled_kernels
    field = ti.field(ti.f64, 3)
    _fill_field(field, 1.5)
    assert np.array_equal(field.to_numpy(), [1.5, 1.5, 1.5])
    assert precompile(_times) == 0 and not _times._primal.compiled_kernels   # (not a variant for k = 0)
    twice = ti.ndarray(ti.f64, 2)
    twice.from_numpy(np.array([1.0, 2.0]))
    _times(twice, 3)
    assert np.array_equal(twice.to_numpy(), [3.0, 6.0])
    kernels = [getattr(dem, name) for name in dem_soil.WARM_KERNELS]
    assert precompile(*kernels) == len(kernels)


@ti.kernel
def _scale_into(k: ti.i32, src: ti.types.ndarray(ti.f64, 1), dst: ti.types.ndarray(ti.f64, 1)):
    for i in range(src.shape[0]):
        dst[i] = k * src[i] + dst[i]


@ti.kernel
def _count_above(limit: ti.f64, a: ti.types.ndarray(ti.f64, 1), out: ti.types.ndarray(ti.i32, 1)):
    out[0] = 0
    for i in range(a.shape[0]):
        if a[i] > limit:
            ti.atomic_add(out[0], 1)


def test_a_kernel_sequence_runs_its_kernels_in_order_as_one_graph_or_one_by_one():
    """backend.KernelSequence (a rebuild's kernels): the arguments bound by name at each run, an array one kernel
    writes read by the next under one name; the compute graph and the launches one by one give the same result, and
    a name given two types is refused when the sequence is built, not found by a wrong result."""
    import pytest

    from opera_taichi.backend import KernelSequence

    if current_arch() is None:
        init_taichi("cpu")
    seq = KernelSequence([(_scale_into, ("k", "x", "y")), (_count_above, ("limit", "y", "count")),
                          (_scale_into, ("k", "y", "x"))])
    assert seq.graph is not None                       # the CPU builds graphs
    results = []
    for run in (seq.run, seq.launch):
        x, y, count = ti.ndarray(ti.f64, 5), ti.ndarray(ti.f64, 5), ti.ndarray(ti.i32, 1)
        x.from_numpy(np.arange(5.0))
        y.from_numpy(np.ones(5))
        run(dict(k=3, limit=6.5, x=x, y=y, count=count))
        results.append((x.to_numpy(), y.to_numpy(), count.to_numpy()))
    for (x, y, count) in results:
        assert np.array_equal(y, 3 * np.arange(5.0) + 1)                    # y = 3 x + y, in that order ...
        assert count[0] == 3                                               # ... counted after it (7, 10, 13) ...
        assert np.array_equal(x, 3 * y + np.arange(5.0))                   # ... then x = 3 y + x
    with pytest.raises(TypeError, match="'x'"):
        KernelSequence([(_scale_into, ("k", "x", "y")), (_count_above, ("x", "y", "count"))])
    with pytest.raises(TypeError, match="3 arguments, 2 names"):
        KernelSequence([(_scale_into, ("k", "x"))])
