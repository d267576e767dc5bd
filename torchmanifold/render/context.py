"""The one place that creates the OpenGL context of the path tracer (headless EGL, GL >= 4.3)."""
from __future__ import annotations

import importlib.util

import moderngl

_default_ctx: moderngl.Context | None = None


def create_context(new: bool = False) -> moderngl.Context:
    """Create (or reuse) a headless OpenGL 4.3+ context for compute shaders.

    On a CPU machine this is Mesa's llvmpipe through EGL; on an NVIDIA machine the same call gives the
    GPU. Loading triton after Mesa's libLLVM segfaults the process, so triton (via ``torch._dynamo``)
    is imported first when it is installed.

    Args:
        new: create a fresh context instead of the process-wide shared one.

    Returns:
        A ``moderngl.Context`` with ``version_code >= 430``.

    Raises:
        RuntimeError: no EGL/OpenGL 4.3 driver (install libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1).
    """
    global _default_ctx
    if not new and _default_ctx is not None:
        return _default_ctx
    if importlib.util.find_spec("triton") is not None:
        import torch._dynamo  # noqa: F401  (loads triton before Mesa's LLVM)
    try:
        ctx = moderngl.create_context(standalone=True, backend="egl", require=430)
    except Exception as exc:
        raise RuntimeError(
            f"could not create a headless OpenGL 4.3 context through EGL ({exc}); "
            "on Debian install libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 libopengl0"
        ) from exc
    # GL objects a garbage-collected tracer leaves are freed the next time this context is made current
    # (make_current): freed at once ("auto"), they were deleted through whichever context was current,
    # e.g. a window's, whose objects with the same names then vanished
    ctx.gc_mode = "context_gc"
    if not new:
        _default_ctx = ctx
    return ctx


def make_current(ctx: moderngl.Context) -> None:
    """Make ``ctx`` the current GL context of this thread and leave it current.

    Another GL user (pyrender, a second context, a window) may have switched contexts. moderngl's
    ``with ctx:`` would restore the previous (possibly no) context on exit, which breaks every later
    plain moderngl call, so only the enter half is used. The objects of ``ctx`` garbage-collected since
    are freed here, with their own context current.
    """
    ctx.__enter__()
    while ctx.objects:  # ctx.gc(), but objects released by hand come back as InvalidObject: skip them
        obj = ctx.objects.popleft()
        if hasattr(obj, "release"):
            obj.release()
