"""How our symbolic loops are traced (Dr.Jit): once per render, with state as wide as
the wavefront.

Dr.Jit records a loop's body a second time in two cases that our loops hit: with its
``OptimizeLoops`` flag (on by default) to drop loop-invariant state, and, even with the
flag off, to drop a state variable that the body leaves unchanged and that is narrower
than the loop (``jit_var_loop_end``). Either doubles the Python tracing of the loop,
and of every loop nested in it. :func:`traced_once` turns the first off around our
renders; :func:`widened` avoids the second.
"""
from __future__ import annotations

import drjit as dr


def traced_once():
    """The scope in which our path loops are traced: Dr.Jit's ``OptimizeLoops`` records
    each symbolic loop a second time to drop its loop-invariant state, so our nested
    loops (path, walk, crossing) were traced up to 2^depth times for kernels that LLVM
    optimises to the same speed (issue 29: 1.4-2.5 ms less Python tracing per render,
    kernel time unchanged; issue 48: a gradient step of 6 views at 32^2 x 8 spp, which
    traces the loops three times per view, 341 -> 226 ms)."""
    return dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, False)


def widened(x, like):
    """``x`` (an array or a ``DRJIT_STRUCT``, changed in place) with every arithmetic or
    mask array of width 1 in it broadcast to the width of the wavefront ``like``
    (literals stay literals: no memory). For a loop's state that its body may leave
    unchanged (a tangent in a primal render, spectral-MIS ratios in a gray medium, a
    ray's time): Dr.Jit records a loop's body a second time to drop an unchanged state
    variable narrower than the loop (``jit_var_loop_end``), even with ``OptimizeLoops``
    off, and that second recording doubled the Python tracing of every render
    (measured: 2 traces of ``volpath_delta``'s body per render, 1 with this)."""
    n = dr.width(like)
    if hasattr(type(x), "DRJIT_STRUCT"):
        for k in type(x).DRJIT_STRUCT:
            setattr(x, k, widened(getattr(x, k), like))
        return x
    if not dr.is_array_v(x) or n <= 1:
        return x
    if dr.depth_v(x) > 1:
        return type(x)(*[widened(c, like) for c in x])
    if dr.width(x) != 1:
        return x
    if dr.is_mask_v(x):
        return x | dr.zeros(type(x), n)
    if dr.is_arithmetic_v(x):
        return x + dr.zeros(type(x), n)
    return x
