"""How the device step's Triton kernels are built and launched.

- :func:`kernel` wraps a kernel's Python function; it is compiled (``triton``'s ``JITFunction``) for CUDA tensors
  and run by Triton's interpreter (``InterpretedFunction``) for CPU tensors, whatever ``TRITON_INTERPRET`` said
  when triton was imported, so the same kernels run in CI without a GPU.
- :func:`device_function` wraps a helper a kernel calls: a ``JITFunction`` the compiler inlines, which under the
  interpreter runs as an interpreted device call (as do ``triton.language``'s own helpers: :func:`_interpreting`).
- :func:`launch` is the one way our kernels start: it counts every launch (:func:`launch_count`,
  :func:`counting`), so a harness counts them exactly on a CPU.

``triton`` is imported on first use, never by ``import eligsir_o3d``.
"""

from __future__ import annotations

import contextlib
import functools

_LAUNCHES = 0  # launches of our kernels since import
_DEPTH = 0  # launches running (nested calls of launch)
_RECORDS: list | None = None  # (kernel, args, meta) of each launch inside recording()


def available() -> bool:
    """Whether ``triton`` imports here."""
    try:
        import triton  # noqa: F401
    except ImportError:
        return False
    return True


def _triton():
    try:
        import triton
    except ImportError as exc:  # pragma: no cover - the torch reference runs instead
        raise ImportError("the fused device step needs triton (pip install triton; CUDA wheels of torch ship it)"
                          ) from exc
    return triton


class Kernel:
    """A Triton kernel's function, compiled for CUDA tensors and interpreted for CPU tensors (each built once)."""

    def __init__(self, fn):
        self.fn = fn
        functools.update_wrapper(self, fn)

    @functools.cached_property
    def compiled(self):
        from triton.runtime.jit import JITFunction

        _triton()
        return JITFunction(self.fn)

    @functools.cached_property
    def interpreted(self):
        from triton.runtime.interpreter import InterpretedFunction

        _triton()
        return InterpretedFunction(self.fn)

    def on(self, device) -> object:
        """The runnable form for tensors on ``device``."""
        return self.interpreted if getattr(device, "type", device) == "cpu" else self.compiled


def kernel(fn) -> Kernel:
    """Decorator: ``fn`` (a Triton kernel body, ``tl`` in its module's globals) as a :class:`Kernel`."""
    return Kernel(fn)


def device_function(fn):
    """Decorator: ``fn`` as a Triton helper our kernels call (a ``JITFunction``: the compiler inlines it; under
    the interpreter it runs as the interpreter's device call, see :func:`_interpreting`)."""
    from triton.runtime.jit import JITFunction

    _triton()
    return JITFunction(fn)


@contextlib.contextmanager
def _interpreting():
    """Inside: every ``JITFunction`` called from an interpreted kernel (our helpers and ``triton.language``'s own,
    ``tl.sum``, ``tl.cumsum``, ...: built as compiled functions when triton was imported without
    ``TRITON_INTERPRET``) runs as an interpreted device call, as it would had that variable been set; and
    ``knobs.runtime.interpret`` reads True. Both are put back on exit."""
    from triton import knobs
    from triton.runtime.interpreter import InterpretedFunction, _patch_lang
    from triton.runtime.jit import JITFunction

    def call(self, *args, **kwargs):  # InterpretedFunction's device call, its language patches undone on return
        f = self.__dict__.get("_interpreted_form")
        if f is None:
            f = self.__dict__["_interpreted_form"] = InterpretedFunction(self.fn)
        scope = _patch_lang(self.fn)
        try:
            return f.rewrite()(*args, **kwargs)
        finally:
            scope.restore()

    saved, was = JITFunction.__call__, knobs.runtime.interpret
    JITFunction.__call__ = call
    knobs.runtime.interpret = True
    try:
        yield
    finally:
        JITFunction.__call__ = saved
        knobs.runtime.interpret = was


def launch(k: Kernel, grid, *args, **meta) -> None:
    """Run kernel ``k`` over ``grid`` (a tuple of program counts) on the device of its first tensor argument,
    counting the launch."""
    global _LAUNCHES
    device = next((a.device for a in args if hasattr(a, "data_ptr")), None)
    if device is None:
        raise ValueError(f"{k.__name__}: no tensor argument to take the device from")
    _LAUNCHES += 1
    global _DEPTH
    _DEPTH += 1
    try:
        _run(k, grid, device, args, meta)
    finally:
        _DEPTH -= 1


def cdiv(a: int, b: int) -> int:
    """``ceil(a / b)`` for the grid sizes (``triton.cdiv``'s value, without its constexpr wrapping on the host)."""
    return -(-int(a) // int(b))


def pow2(n: int) -> int:
    """The smallest power of two >= ``n`` (``triton.next_power_of_2``'s value, plain Python)."""
    return 1 << max(0, int(n) - 1).bit_length()


def in_launch() -> bool:
    """Whether a launch of ours is running (under the interpreter its torch operators are the kernel's own work)."""
    return _DEPTH > 0


def _run(k: Kernel, grid, device, args, meta) -> None:
    if _RECORDS is not None:
        _RECORDS.append((k, args, meta))
    if device.type == "cpu":
        with _interpreting():
            k.interpreted[tuple(grid)](*args, **meta)
    else:
        k.compiled[tuple(grid)](*args, **meta)


def launch_count() -> int:
    """Launches of our kernels since import."""
    return _LAUNCHES


class LaunchCounter:
    """The launches counted inside a :func:`counting` block (``n``)."""

    def __init__(self):
        self.start = _LAUNCHES
        self.stop: int | None = None

    @property
    def n(self) -> int:
        return (_LAUNCHES if self.stop is None else self.stop) - self.start


@contextlib.contextmanager
def counting():
    """``with counting() as c: ...``; then ``c.n`` is the number of our kernel launches inside the block."""
    c = LaunchCounter()
    try:
        yield c
    finally:
        c.stop = _LAUNCHES


@contextlib.contextmanager
def recording():
    """``with recording() as launches: ...``; then ``launches`` lists (kernel, args, meta) of every launch."""
    global _RECORDS
    saved, _RECORDS = _RECORDS, []
    try:
        yield _RECORDS
    finally:
        _RECORDS = saved


def _arg_type(a):
    import torch

    if isinstance(a, torch.Tensor):
        names = {torch.float32: "fp32", torch.float64: "fp64", torch.int64: "i64", torch.int32: "i32",
                 torch.int8: "i8", torch.uint8: "u8", torch.bool: "i1"}
        return "*" + names[a.dtype]
    if isinstance(a, bool):
        return "i1"
    if isinstance(a, int):
        return "i64"
    if isinstance(a, float):
        return "fp32"
    if isinstance(a, tuple):
        return tuple(_arg_type(x) for x in a)
    raise TypeError(f"no Triton type for {type(a).__name__}")


def compile_for_cuda(k: Kernel, args, meta, arch: int = 90):
    """Compile ``k`` as it would launch with ``args``/``meta`` for CUDA compute capability ``arch``, on this
    machine (no GPU needed: Triton's own ptxas builds the cubin). Returns the compiled kernel (``.asm``)."""
    import inspect

    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    triton = _triton()
    sig = {name: _arg_type(a) for name, a in zip(inspect.signature(k.fn).parameters, args)}
    sig.update({name: "constexpr" for name in meta})
    return triton.compile(ASTSource(k.compiled, sig, dict(meta)), target=GPUTarget("cuda", arch, 32))
