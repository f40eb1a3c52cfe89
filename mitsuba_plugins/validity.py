"""Invalid-sample accounting: every sample whose radiance is NaN or Inf is counted in the
kernel and replaced by 0, so an image is never silently wrong.

Mitsuba's JIT variants do not check the film: a NaN sample makes its pixel NaN, and any
later averaging or tone mapping hides where it came from. Our integrators call
their :class:`SampleGuard` on their ``sample()`` result; :func:`counted` wraps any other
integrator (Mitsuba's built-ins) so that the CLI and the benchmarks count theirs the same
way. :func:`take_invalid_samples` reads and resets a counter after a render.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

VARIANT = mi.variant()


def refuse_gradients(plugin: str, alternative: str) -> tuple:
    """``(render_forward, render_backward)`` for a plugin class whose gradients would be
    silently wrong: differentiating its render (``mi.render(..., params=...)`` followed by
    ``dr.forward`` / ``dr.backward``) raises one line naming the integrator to use.

    Measured before (issue 14.7): d(mean image)/d(density grid) of a 32x32 render of an
    8^3 ``grid_medium`` cube was +5.4e-4 with ``prbvolpath``, -5.9e-12 with volpath_delta
    and -1.1e-4 with volpath_raymarch.
    """
    message = (f"{plugin}: differentiable rendering is not supported (its gradients would "
               f"be wrong); render the gradient with Mitsuba's '{alternative}' integrator")

    def render_forward(self, *args, **kwargs):
        raise NotImplementedError(message)

    def render_backward(self, *args, **kwargs):
        raise NotImplementedError(message)

    return render_forward, render_backward


class SampleGuard:
    """An in-kernel counter of NaN/Inf samples, held by a sampling integrator as
    ``self.sample_guard`` (nanobind classes take one base, so this is a member, not a
    mixin).

    The counter is one ``UInt32`` that :meth:`__call__` adds to with a masked atomic
    scatter; lanes with finite values take no part, so a healthy render pays one test per
    sample. The counter is an ordinary kernel input: replacing it does not recompile.
    """

    def __init__(self):
        self.counter = None

    def __call__(self, L: mi.Spectrum, active: mi.Bool) -> mi.Spectrum:
        """``L`` with NaN/Inf samples (in any channel) counted and set to 0."""
        if self.counter is None:
            self.counter = dr.zeros(mi.UInt32, 1)
        bad = mi.Bool(active) & ~dr.all(dr.isfinite(L))
        dr.scatter_reduce(dr.ReduceOp.Add, self.counter, mi.UInt32(1), mi.UInt32(0), bad)
        return dr.select(bad, 0.0, L)

    def take(self) -> int:
        """NaN/Inf samples since the last call (evaluates the pending kernel)."""
        if self.counter is None:
            return 0
        count = int(self.counter[0])
        self.counter = None
        return count


class Counted(mi.SamplingIntegrator):
    """Any sampling integrator, its samples counted and guarded (see :func:`counted`)."""

    def __init__(self, inner: mi.SamplingIntegrator):
        super().__init__(mi.Properties())
        self.inner = inner
        self.sample_guard = SampleGuard()

    def sample(self, scene, sampler, ray, medium=None, active=True):
        L, valid, aovs = self.inner.sample(scene, sampler, ray, medium, active)
        return self.sample_guard(L, active), valid, aovs

    def aov_names(self):
        return self.inner.aov_names()

    def to_string(self):
        return f"Counted[{self.inner}]"


def counted(integrator):
    """``integrator`` if it counts its own invalid samples, else a counting wrapper.

    Integrators that are not sampling integrators are returned unchanged (their samples
    are not counted; :func:`take_invalid_samples` returns None for them).
    """
    if integrator is None or hasattr(integrator, "sample_guard"):
        return integrator
    if isinstance(integrator, mi.SamplingIntegrator):
        return Counted(integrator)
    return integrator


def take_invalid_samples(integrator) -> int | None:
    """Invalid samples counted by ``integrator`` since the last call; None if it cannot count."""
    guard = getattr(integrator, "sample_guard", None)
    return guard.take() if guard is not None else None
